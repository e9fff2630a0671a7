"use strict";
// The operator's password goes to /api/login once; the session lives in an HttpOnly cookie.
document.getElementById("login").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const form = ev.target;
  const error = document.getElementById("login-error");
  error.textContent = "";
  const res = await fetch("/api/login", {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ username: form.username.value, password: form.password.value }),
  });
  if (res.ok) {
    window.location.assign("/");
  } else {
    const body = await res.json().catch(() => ({}));
    error.textContent = body.error || `login failed (${res.status})`;
  }
});

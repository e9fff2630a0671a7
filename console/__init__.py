"""The operator's console: a live web page and terminal commands over the site's MQTT contract."""

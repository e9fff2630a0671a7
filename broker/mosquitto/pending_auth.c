/* wsnav's pending-password plugin for Mosquitto 2.0 (plugin API 5; built against Debian's mosquitto-dev and
 * libssl-dev by `wsnav broker mosquitto-config --pending-passwords`, broker/mosquitto/pending_plugin.py).
 *
 * Why: Mosquitto's password file holds one password per user, so a node changing its MQTT password over the
 * air (`wsnav firmware config --new-password`) would be locked out between the moment it switches and the
 * moment the password file and a SIGHUP catch up. This plugin accepts, beside the password file, the passwords
 * listed in `plugin_opt_pending_file` (`username:$7$...` lines, mosquitto_passwd's PBKDF2-SHA512 format): the
 * operator's tool adds a node's new password there before the node tries it and removes it once the password file
 * has it. The file is read at each login (no SIGHUP; a missing or unreadable file: no pending passwords), and a
 * login it does not match is deferred to the password file, which decides as without the plugin.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <openssl/crypto.h>
#include <openssl/evp.h>

#include <mosquitto.h>
#include <mosquitto_broker.h>
#include <mosquitto_plugin.h>

static mosquitto_plugin_id_t *plugin_id = NULL;
static char *pending_file = NULL;

/* base64 `in` into `out` (at most `cap` bytes): its length, or -1. */
static int decode(const char *in, unsigned char *out, int cap)
{
	size_t len = strlen(in);
	unsigned char buf[128];
	int n, pad = 0;

	if(len == 0 || len % 4 != 0 || len / 4 * 3 > sizeof(buf)) return -1;
	n = EVP_DecodeBlock(buf, (const unsigned char *)in, (int)len);
	if(n < 0) return -1;
	if(in[len - 1] == '=') pad++;
	if(in[len - 2] == '=') pad++;
	n -= pad;
	if(n > cap) return -1;
	memcpy(out, buf, (size_t)n);
	return n;
}

/* Does `line` (`username:$7$iterations$salt$hash`, modified here) give `username` the password `password`? */
static int matches(char *line, const char *username, const char *password)
{
	char *hash, *fields[3];
	unsigned char salt[64], want[64], got[64];
	int salt_len, want_len, i;
	long iterations;

	hash = strchr(line, ':');
	if(!hash) return 0;
	*hash++ = '\0';
	if(strcmp(line, username) != 0 || strncmp(hash, "$7$", 3) != 0) return 0;
	fields[0] = hash + 3;
	for(i = 1; i < 3; i++){
		fields[i] = strchr(fields[i - 1], '$');
		if(!fields[i]) return 0;
		*fields[i]++ = '\0';
	}
	iterations = strtol(fields[0], NULL, 10);
	salt_len = decode(fields[1], salt, sizeof(salt));
	want_len = decode(fields[2], want, sizeof(want));
	if(iterations < 1 || iterations > 100000 || salt_len < 1 || want_len != 64) return 0;
	if(!PKCS5_PBKDF2_HMAC(password, (int)strlen(password), salt, salt_len, (int)iterations, EVP_sha512(),
			64, got)){
		return 0;
	}
	return CRYPTO_memcmp(got, want, 64) == 0;
}

static int on_basic_auth(int event, void *event_data, void *userdata)
{
	struct mosquitto_evt_basic_auth *ed = event_data;
	char line[512];
	FILE *f;
	int ok = 0;

	(void)event;
	(void)userdata;
	if(!ed->username || !ed->password) return MOSQ_ERR_PLUGIN_DEFER;
	f = fopen(pending_file, "r");
	if(!f) return MOSQ_ERR_PLUGIN_DEFER;
	while(!ok && fgets(line, sizeof(line), f)){
		line[strcspn(line, "\r\n")] = '\0';
		ok = line[0] != '#' && matches(line, ed->username, ed->password);
	}
	fclose(f);
	return ok ? MOSQ_ERR_SUCCESS : MOSQ_ERR_PLUGIN_DEFER;
}

int mosquitto_plugin_version(int supported_version_count, const int *supported_versions)
{
	(void)supported_version_count;
	(void)supported_versions;
	return 5;
}

int mosquitto_plugin_init(mosquitto_plugin_id_t *identifier, void **userdata, struct mosquitto_opt *opts,
		int opt_count)
{
	int i;

	(void)userdata;
	for(i = 0; i < opt_count; i++){
		if(strcmp(opts[i].key, "pending_file") == 0){
			pending_file = mosquitto_strdup(opts[i].value);
		}
	}
	if(!pending_file){
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav pending passwords: plugin_opt_pending_file is missing");
		return MOSQ_ERR_INVAL;
	}
	plugin_id = identifier;
	return mosquitto_callback_register(plugin_id, MOSQ_EVT_BASIC_AUTH, on_basic_auth, NULL, NULL);
}

int mosquitto_plugin_cleanup(void *userdata, struct mosquitto_opt *opts, int opt_count)
{
	(void)userdata;
	(void)opts;
	(void)opt_count;
	mosquitto_callback_unregister(plugin_id, MOSQ_EVT_BASIC_AUTH, on_basic_auth, NULL);
	mosquitto_free(pending_file);
	pending_file = NULL;
	return MOSQ_ERR_SUCCESS;
}

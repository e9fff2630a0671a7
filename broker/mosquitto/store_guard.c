/*
 * wsnav's Mosquitto plugin (built by `wsnav broker mosquitto-plugin`, against Debian's mosquitto-dev 2.0.11).
 *
 * Why: Mosquitto acknowledges a retained message before its next store save (every 2 s at best), so an operator
 * block acknowledged just before a power cut was lost; and on a full disk Mosquitto 2.0.11 replaces its store by
 * a cut-short file without a word in its log. This plugin
 *  - journals every retained message under `topic_prefix` (the operator blocks) with fdatasync BEFORE Mosquitto
 *    sends the PUBACK (MOSQ_EVT_MESSAGE runs after the ACL check and before the acknowledgement), and at start
 *    publishes the latest of each topic again (after the store was read), so a block, or its lifting, that was
 *    acknowledged is what the broker serves after a kill -9;
 *  - once a second (MOSQ_EVT_TICK) checks the disk has room for the next save and walks a newly saved store's
 *    chunk framing (the rule of broker/mosquitto/store.py), logging an ERROR line in Mosquitto's own log when
 *    either fails, and hard-links a whole store as mosquitto.db.good for `wsnav broker mosquitto-restore`.
 *
 * Options (mosquitto.conf): plugin_opt_journal FILE, plugin_opt_topic_prefix PREFIX, plugin_opt_store FILE.
 * Journal: "WSNAVBJ1", then records of a big-endian u32 topic length, u32 payload length, u32 CRC-32 of topic
 * and payload, the topic, the payload. A torn last record (a power cut inside a write that was never
 * acknowledged) is cut off; the journal is rewritten with the latest record of each topic at every start.
 */
#include <errno.h>
#include <fcntl.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <time.h>
#include <unistd.h>

#include <mosquitto.h>
#include <mosquitto_broker.h>
#include <mosquitto_plugin.h>

#define JOURNAL_MAGIC "WSNAVBJ1"
#define MAGIC_BYTES 8
#define RECORD_HEAD 12
#define MAX_TOPIC 65535u
#define MAX_PAYLOAD (256u * 1024u * 1024u)
#define STORE_MAGIC "\x00\xb5\x00mosquitto db"
#define STORE_MAGIC_BYTES 15
#define STORE_HEADER_BYTES (STORE_MAGIC_BYTES + 8)
#define CHUNK_CFG 1u
#define ROOM_MARGIN (64 * 1024)
#define REPEAT_S 60 /* a problem that lasts is logged again this often, not at every save */

struct record {
	char *topic;
	uint8_t *payload;
	uint32_t payloadlen;
};

static mosquitto_plugin_id_t *plugin_id;
static char *journal_path, *prefix, *store_path;
static size_t prefix_len;
static int journal_fd = -1;
static struct record *latest;
static size_t latest_count, latest_cap;
static time_t last_check;
static struct timespec store_seen;
static off_t store_seen_size = -1;
static bool store_bad, room_short;
static time_t store_bad_logged, room_short_logged;

static uint32_t crc32_of(uint32_t crc, const uint8_t *data, size_t len)
{
	crc = ~crc;
	for(size_t i = 0; i < len; i++){
		crc ^= data[i];
		for(int k = 0; k < 8; k++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
	}
	return ~crc;
}

static void put_u32(uint8_t *out, uint32_t v)
{
	out[0] = (uint8_t)(v >> 24); out[1] = (uint8_t)(v >> 16); out[2] = (uint8_t)(v >> 8); out[3] = (uint8_t)v;
}

static uint32_t get_u32(const uint8_t *in)
{
	return ((uint32_t)in[0] << 24) | ((uint32_t)in[1] << 16) | ((uint32_t)in[2] << 8) | (uint32_t)in[3];
}

static int write_all(int fd, const uint8_t *data, size_t len)
{
	while(len > 0){
		ssize_t n = write(fd, data, len);
		if(n < 0){
			if(errno == EINTR) continue;
			return -1;
		}
		data += n;
		len -= (size_t)n;
	}
	return 0;
}

static int read_all(int fd, uint8_t *data, size_t len)
{
	while(len > 0){
		ssize_t n = read(fd, data, len);
		if(n < 0 && errno == EINTR) continue;
		if(n <= 0) return -1;
		data += n;
		len -= (size_t)n;
	}
	return 0;
}

/* One record, its head and body in one write, so a record is either whole or a torn tail. */
static int write_record(int fd, const char *topic, const uint8_t *payload, uint32_t payloadlen)
{
	size_t topiclen = strlen(topic);
	size_t total = RECORD_HEAD + topiclen + payloadlen;
	uint8_t *buf = malloc(total);
	if(buf == NULL){
		errno = ENOMEM;
		return -1;
	}
	uint32_t crc = crc32_of(crc32_of(0, (const uint8_t *)topic, topiclen), payload, payloadlen);
	put_u32(buf, (uint32_t)topiclen);
	put_u32(buf + 4, payloadlen);
	put_u32(buf + 8, crc);
	memcpy(buf + RECORD_HEAD, topic, topiclen);
	if(payloadlen) memcpy(buf + RECORD_HEAD + topiclen, payload, payloadlen);
	int rc = write_all(fd, buf, total);
	free(buf);
	return rc;
}

static int remember(char *topic, uint8_t *payload, uint32_t payloadlen)
{
	for(size_t i = 0; i < latest_count; i++){
		if(strcmp(latest[i].topic, topic) == 0){
			free(latest[i].topic);
			free(latest[i].payload);
			latest[i] = (struct record){topic, payload, payloadlen};
			return 0;
		}
	}
	if(latest_count == latest_cap){
		size_t cap = latest_cap ? latest_cap * 2 : 16;
		struct record *grown = realloc(latest, cap * sizeof(*grown));
		if(grown == NULL) return -1;
		latest = grown;
		latest_cap = cap;
	}
	latest[latest_count++] = (struct record){topic, payload, payloadlen};
	return 0;
}

/* Reads the journal's whole records into `latest`; returns the length of its whole part (0: no journal). */
static off_t read_journal(void)
{
	int fd = open(journal_path, O_RDONLY | O_CLOEXEC);
	if(fd < 0){
		if(errno != ENOENT){
			mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: cannot read the operator-block journal %s: %s",
					journal_path, strerror(errno));
		}
		return 0;
	}
	uint8_t head[RECORD_HEAD];
	if(read_all(fd, head, MAGIC_BYTES) || memcmp(head, JOURNAL_MAGIC, MAGIC_BYTES)){
		close(fd);
		size_t len = strlen(journal_path) + 9;
		char *aside = malloc(len);
		if(aside != NULL){
			snprintf(aside, len, "%s.damaged", journal_path);
			if(rename(journal_path, aside) != 0){
				free(aside);
				aside = NULL;
			}
		}
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: ERROR: %s is not an operator-block journal: moved to %s, "
				"no block restored from it (the store's are served)", journal_path, aside ? aside : "(could not move)");
		free(aside);
		return 0;
	}
	off_t whole = MAGIC_BYTES;
	while(read_all(fd, head, RECORD_HEAD) == 0){
		uint32_t topiclen = get_u32(head), payloadlen = get_u32(head + 4), crc = get_u32(head + 8);
		if(topiclen == 0 || topiclen > MAX_TOPIC || payloadlen > MAX_PAYLOAD) break;
		char *topic = malloc(topiclen + 1);
		uint8_t *payload = malloc(payloadlen + 1);
		if(topic == NULL || payload == NULL || read_all(fd, (uint8_t *)topic, topiclen)
				|| (payloadlen && read_all(fd, payload, payloadlen))
				|| crc32_of(crc32_of(0, (uint8_t *)topic, topiclen), payload, payloadlen) != crc){
			free(topic);
			free(payload);
			break;
		}
		topic[topiclen] = '\0';
		if(remember(topic, payload, payloadlen)){
			free(topic);
			free(payload);
			break;
		}
		whole += RECORD_HEAD + topiclen + payloadlen;
	}
	close(fd);
	return whole;
}

static void sync_folder_of(const char *path)
{
	char *copy = strdup(path);
	if(copy == NULL) return;
	char *slash = strrchr(copy, '/');
	if(slash == copy) slash[1] = '\0';
	else if(slash) *slash = '\0';
	else strcpy(copy, ".");
	int fd = open(copy, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
	if(fd >= 0){
		fsync(fd);
		close(fd);
	}
	free(copy);
}

/* The latest record of each topic into FILE.new, synced and renamed over the journal. */
static int compact_journal(void)
{
	size_t len = strlen(journal_path) + 5;
	char *fresh = malloc(len);
	if(fresh == NULL) return -1;
	snprintf(fresh, len, "%s.new", journal_path);
	int fd = open(fresh, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
	int rc = fd < 0 ? -1 : write_all(fd, (const uint8_t *)JOURNAL_MAGIC, MAGIC_BYTES);
	for(size_t i = 0; rc == 0 && i < latest_count; i++){
		rc = write_record(fd, latest[i].topic, latest[i].payload, latest[i].payloadlen);
	}
	if(rc == 0) rc = fdatasync(fd);
	if(fd >= 0 && close(fd) && rc == 0) rc = -1;
	if(rc == 0) rc = rename(fresh, journal_path);
	if(rc == 0) sync_folder_of(journal_path);
	else unlink(fresh);
	free(fresh);
	return rc;
}

static int open_journal(void)
{
	off_t whole = read_journal();
	if(compact_journal() != 0){
		int why = errno;
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: cannot rewrite the operator-block journal %s: %s; "
				"appending to it as it is", journal_path, strerror(why));
		journal_fd = open(journal_path, O_WRONLY | O_CREAT | O_CLOEXEC, 0600);
		if(journal_fd < 0) return -1;
		if(whole == 0){
			if(ftruncate(journal_fd, 0) || write_all(journal_fd, (const uint8_t *)JOURNAL_MAGIC, MAGIC_BYTES)){
				return -1;
			}
		}else if(ftruncate(journal_fd, whole)){
			return -1;
		}
		return lseek(journal_fd, 0, SEEK_END) < 0 ? -1 : 0;
	}
	journal_fd = open(journal_path, O_WRONLY | O_APPEND | O_CLOEXEC);
	return journal_fd < 0 ? -1 : 0;
}

static bool is_journaled(const char *topic)
{
	return topic != NULL && strncmp(topic, prefix, prefix_len) == 0 && topic[prefix_len] != '\0'
			&& strchr(topic + prefix_len, '/') == NULL;
}

static int on_message(int event, void *event_data, void *userdata)
{
	(void)event;
	(void)userdata;
	struct mosquitto_evt_message *ed = event_data;
	if(!ed->retain || !is_journaled(ed->topic)) return MOSQ_ERR_SUCCESS;
	off_t before = lseek(journal_fd, 0, SEEK_END);
	if(before >= 0 && write_record(journal_fd, ed->topic, ed->payload, ed->payloadlen) == 0
			&& fdatasync(journal_fd) == 0){
		return MOSQ_ERR_SUCCESS;
	}
	int why = errno;
	if(before >= 0 && ftruncate(journal_fd, before) == 0) fdatasync(journal_fd);
	/* Served anyway: a block in force now matters more than one that survives a power cut. */
	mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: ERROR: operator block %s from %s NOT journaled (%s): it is in "
			"force but will not survive a power cut; free the disk of %s and send it again", ed->topic,
			mosquitto_client_id(ed->client), strerror(why), journal_path);
	return MOSQ_ERR_SUCCESS;
}

/* 0: whole; else a few words on what is wrong (the rule of broker/mosquitto/store.py's check_store). */
static const char *store_problem(int fd, off_t size)
{
	uint8_t head[STORE_HEADER_BYTES];
	if(size == 0) return "empty (0 bytes)";
	if(size < STORE_HEADER_BYTES || pread(fd, head, STORE_HEADER_BYTES, 0) != STORE_HEADER_BYTES
			|| memcmp(head, STORE_MAGIC, STORE_MAGIC_BYTES)){
		return "not a Mosquitto store";
	}
	off_t pos = STORE_HEADER_BYTES;
	bool config = false;
	while(pos < size){
		if(pos + 8 > size || pread(fd, head, 8, pos) != 8) return "cut short (a chunk header is incomplete)";
		config = config || get_u32(head) == CHUNK_CFG;
		pos += 8 + (off_t)get_u32(head + 4);
		if(pos > size) return "cut short (a chunk runs past its end)";
	}
	return config ? NULL : "cut short (no config chunk)";
}

static void keep_good(void)
{
	size_t len = strlen(store_path) + 32;
	char *good = malloc(len), *temporary = malloc(len);
	if(good && temporary){
		snprintf(good, len, "%s.good", store_path);
		snprintf(temporary, len, "%s.good.%ld", store_path, (long)getpid());
		unlink(temporary);
		if(link(store_path, temporary) == 0 && rename(temporary, good) != 0) unlink(temporary);
	}
	free(good);
	free(temporary);
}

static void check_store(void)
{
	struct stat st;
	if(stat(store_path, &st) != 0) return; /* not saved yet */
	struct statvfs fs;
	if(statvfs(store_path, &fs) == 0){
		unsigned long long room = (unsigned long long)fs.f_bavail * fs.f_frsize;
		unsigned long long need = 2ull * (unsigned long long)st.st_size + ROOM_MARGIN;
		time_t now = time(NULL);
		if(room < need && (!room_short || now - room_short_logged >= REPEAT_S)){
			room_short_logged = now;
			mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: ERROR: the disk of %s is full (%llu bytes free, the next "
					"save needs about %llu): Mosquitto's next save will be cut short; free the disk",
					store_path, room, need);
		}else if(room >= need && room_short){
			mosquitto_log_printf(MOSQ_LOG_NOTICE, "wsnav: the disk of %s has room for the store again", store_path);
		}
		room_short = room < need;
	}
	if(st.st_mtim.tv_sec == store_seen.tv_sec && st.st_mtim.tv_nsec == store_seen.tv_nsec
			&& st.st_size == store_seen_size){
		return;
	}
	store_seen = st.st_mtim;
	store_seen_size = st.st_size;
	int fd = open(store_path, O_RDONLY | O_CLOEXEC);
	if(fd < 0) return;
	const char *problem = store_problem(fd, st.st_size);
	close(fd);
	time_t now = time(NULL);
	if(problem != NULL && (!store_bad || now - store_bad_logged >= REPEAT_S)){
		store_bad_logged = now;
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: ERROR: %s was saved %s (a full disk?): a restart would lose "
				"every retained message; the last whole store is kept as %s.good (`wsnav broker "
				"mosquitto-restore` puts it back before a start)", store_path, problem, store_path);
	}else if(problem == NULL){
		if(store_bad) mosquitto_log_printf(MOSQ_LOG_NOTICE, "wsnav: %s is whole again", store_path);
		keep_good();
	}
	store_bad = problem != NULL;
}

static int on_tick(int event, void *event_data, void *userdata)
{
	(void)event;
	(void)event_data;
	(void)userdata;
	time_t now = time(NULL);
	if(store_path != NULL && now != last_check){
		last_check = now;
		check_store();
	}
	return MOSQ_ERR_SUCCESS;
}

int mosquitto_plugin_version(int supported_version_count, const int *supported_versions)
{
	for(int i = 0; i < supported_version_count; i++){
		if(supported_versions[i] == 5) return 5;
	}
	return -1;
}

int mosquitto_plugin_init(mosquitto_plugin_id_t *identifier, void **userdata, struct mosquitto_opt *options,
		int option_count)
{
	(void)userdata;
	plugin_id = identifier;
	for(int i = 0; i < option_count; i++){
		if(strcmp(options[i].key, "journal") == 0) journal_path = options[i].value;
		else if(strcmp(options[i].key, "topic_prefix") == 0) prefix = options[i].value;
		else if(strcmp(options[i].key, "store") == 0) store_path = options[i].value;
	}
	if(journal_path == NULL || prefix == NULL || prefix[0] == '\0'){
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: the plugin needs plugin_opt_journal and plugin_opt_topic_prefix");
		return MOSQ_ERR_INVAL;
	}
	prefix_len = strlen(prefix);
	if(open_journal() != 0){
		mosquitto_log_printf(MOSQ_LOG_ERR, "wsnav: cannot open the operator-block journal %s: %s", journal_path,
				strerror(errno));
		return MOSQ_ERR_UNKNOWN;
	}
	size_t restored = 0;
	for(size_t i = 0; i < latest_count; i++){
		/* An empty payload clears the topic: a lifting acknowledged after the store's last save. */
		if(mosquitto_broker_publish_copy(NULL, latest[i].topic, (int)latest[i].payloadlen, latest[i].payload, 1,
				true, NULL) == MOSQ_ERR_SUCCESS){
			restored += latest[i].payloadlen > 0;
		}
		free(latest[i].topic);
		free(latest[i].payload);
	}
	free(latest);
	latest = NULL;
	latest_count = latest_cap = 0;
	mosquitto_log_printf(MOSQ_LOG_NOTICE, "wsnav: operator-block journal %s: %zu blocks in force restored",
			journal_path, restored);
	int rc = mosquitto_callback_register(plugin_id, MOSQ_EVT_MESSAGE, on_message, NULL, NULL);
	if(rc == MOSQ_ERR_SUCCESS && store_path != NULL){
		rc = mosquitto_callback_register(plugin_id, MOSQ_EVT_TICK, on_tick, NULL, NULL);
	}
	return rc;
}

int mosquitto_plugin_cleanup(void *userdata, struct mosquitto_opt *options, int option_count)
{
	(void)userdata;
	(void)options;
	(void)option_count;
	mosquitto_callback_unregister(plugin_id, MOSQ_EVT_MESSAGE, on_message, NULL);
	if(store_path != NULL) mosquitto_callback_unregister(plugin_id, MOSQ_EVT_TICK, on_tick, NULL);
	if(journal_fd >= 0) close(journal_fd);
	journal_fd = -1;
	return MOSQ_ERR_SUCCESS;
}

/* A Cyclone DDS 0.10 peer of `wsnav ros2 bridge` (tests/test_ros2_dds_peers.py): Debian's libddsc, as ROS 2
 * Humble and Jazzy ship it (0.10.x). Modes: "reader" reads rt/<topic> as rmw_cyclonedds reads a map (reliable,
 * transient_local, keep-last DEPTH, XCDR1 only, "enclave=/;" user data); "bare" is a participant with no endpoints.
 * Whether the reader carries type information is decided at compile time (idlc with or without -t).
 * One JSON line per sample on stdout: the grid's size, frame and an FNV-1a hash of its data. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "dds/dds.h"
#include "ros2_grid.h"

static volatile sig_atomic_t stop = 0;
static void on_term(int sig) { (void)sig; stop = 1; }

int main(int argc, char **argv) {
  if (argc < 3) { fprintf(stderr, "usage: %s reader|bare DOMAIN [TOPIC DEPTH]\n", argv[0]); return 2; }
  setvbuf(stdout, NULL, _IOLBF, 0);
  signal(SIGTERM, on_term);
  signal(SIGINT, on_term);
  dds_qos_t *pqos = dds_create_qos();
  dds_qset_userdata(pqos, "enclave=/;", strlen("enclave=/;"));
  dds_entity_t pp = dds_create_participant((dds_domainid_t)atoi(argv[2]), pqos, NULL);
  dds_delete_qos(pqos);
  if (pp < 0) { fprintf(stderr, "participant: %s\n", dds_strretcode(pp)); return 1; }
  dds_entity_t rd = 0;
  if (strcmp(argv[1], "reader") == 0) {
    if (argc < 5) { fprintf(stderr, "reader needs TOPIC DEPTH\n"); return 2; }
    dds_entity_t tp = dds_create_topic(pp, &nav_msgs_msg_dds__OccupancyGrid__desc, argv[3], NULL, NULL);
    if (tp < 0) { fprintf(stderr, "topic: %s\n", dds_strretcode(tp)); return 1; }
    dds_qos_t *qos = dds_create_qos();
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
    dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
    dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, atoi(argv[4]));
    dds_data_representation_id_t xcdr1 = DDS_DATA_REPRESENTATION_XCDR1;
    dds_qset_data_representation(qos, 1, &xcdr1);
    rd = dds_create_reader(pp, tp, qos, NULL);
    dds_delete_qos(qos);
    if (rd < 0) { fprintf(stderr, "reader: %s\n", dds_strretcode(rd)); return 1; }
  } else if (strcmp(argv[1], "bare") != 0) {
    fprintf(stderr, "unknown mode %s\n", argv[1]);
    return 2;
  }
  printf("{\"ready\": true}\n");
  void *samples[1] = {NULL};
  dds_sample_info_t infos[1];
  while (!stop) {
    if (rd > 0) {
      dds_return_t n;
      while ((n = dds_take(rd, samples, infos, 1, 1)) > 0) {
        if (infos[0].valid_data) {
          const nav_msgs_msg_dds__OccupancyGrid_ *g = samples[0];
          uint32_t h = 2166136261u;
          for (uint32_t i = 0; i < g->data._length; i++) { h ^= (uint8_t)g->data._buffer[i]; h *= 16777619u; }
          printf("{\"width\": %u, \"height\": %u, \"length\": %u, \"frame_id\": \"%s\", \"fnv1a\": %u}\n",
                 g->info.width, g->info.height, g->data._length, g->header.frame_id, h);
        }
        dds_return_loan(rd, samples, n);
        samples[0] = NULL;
      }
    }
    dds_sleepfor(DDS_MSECS(20));
  }
  dds_delete(pp);
  return 0;
}

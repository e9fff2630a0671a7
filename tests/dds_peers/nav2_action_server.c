/* A stand-in for Nav2's bt_navigator on Debian's Cyclone DDS 0.10.2 (what Humble's and Jazzy's rmw_cyclonedds
 * run on), for tests/test_ros2_nav2.py: the navigate_to_pose action server as rclcpp lays it out on
 * rmw_cyclonedds (rq/.../_action/send_goalRequest and cancel_goalRequest read, rr/...Reply written with the
 * request's header repeated, rt/.../_action/status reliable + transient_local + depth 1), and AMCL's /amcl_pose.
 *
 * It behaves as bt_navigator does towards its clients: every goal accepted (status ACCEPTED, then EXECUTING);
 * a new goal aborts the one executing (nav2_util's SimpleActionServer preempts so); a cancel of an executing goal
 * ends it CANCELED (reply ERROR_NONE with the goal), of another one answers ERROR_GOAL_TERMINATED or
 * ERROR_UNKNOWN_GOAL_ID. What it leaves out of bt_navigator is said in the test.
 *
 * stdin, one command a line: "pose X Y YAW" publishes /amcl_pose; "plan X0 Y0 X1 Y1" publishes /plan (reliable,
 * volatile, depth 1, as planner_server), a straight line of 5 cm steps; "succeed" ends the executing goal
 * SUCCEEDED.
 * stdout, one JSON line each: {"ready": true}; every goal request and every cancel request it took. */
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include "dds/dds.h"
#include "nav2_action.h"

enum { UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED };
#define MAX_GOALS 64

typedef nav2_msgs_action_dds__NavigateToPose_SendGoal_Request_ GoalRequest;
typedef nav2_msgs_action_dds__NavigateToPose_SendGoal_Response_ GoalReply;
typedef action_msgs_srv_dds__CancelGoal_Request_ CancelRequest;
typedef action_msgs_srv_dds__CancelGoal_Response_ CancelReply;

static volatile sig_atomic_t stop = 0;
static void on_term(int sig) { (void)sig; stop = 1; }

static action_msgs_msg_dds__GoalStatus_ goals[MAX_GOALS];
static uint32_t n_goals = 0;
static int executing = -1;

static void hex(const uint8_t *b, char *out) { for (int i = 0; i < 16; i++) sprintf(out + 2 * i, "%02x", b[i]); }

static void publish_status(dds_entity_t wr) {
  action_msgs_msg_dds__GoalStatusArray_ msg;
  msg.status_list._length = msg.status_list._maximum = n_goals;
  msg.status_list._buffer = goals;
  msg.status_list._release = false;
  dds_write(wr, &msg);
}

static dds_qos_t *qos_of(dds_durability_kind_t durability, int32_t depth) {
  dds_qos_t *qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  dds_qset_durability(qos, durability);
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, depth);
  dds_data_representation_id_t xcdr1 = DDS_DATA_REPRESENTATION_XCDR1;
  dds_qset_data_representation(qos, 1, &xcdr1);
  return qos;
}

static dds_entity_t endpoint(dds_entity_t pp, const dds_topic_descriptor_t *desc, const char *name, dds_qos_t *qos,
                             int writer) {
  dds_entity_t tp = dds_create_topic(pp, desc, name, NULL, NULL);
  if (tp < 0) { fprintf(stderr, "topic %s: %s\n", name, dds_strretcode(tp)); exit(1); }
  dds_entity_t e = writer ? dds_create_writer(pp, tp, qos, NULL) : dds_create_reader(pp, tp, qos, NULL);
  if (e < 0) { fprintf(stderr, "endpoint %s: %s\n", name, dds_strretcode(e)); exit(1); }
  return e;
}

static void end_executing(int status) {
  if (executing >= 0) goals[executing].status = (int8_t)status;
  executing = -1;
}

int main(int argc, char **argv) {
  if (argc < 2) { fprintf(stderr, "usage: %s DOMAIN\n", argv[0]); return 2; }
  setvbuf(stdout, NULL, _IOLBF, 0);
  signal(SIGTERM, on_term);
  signal(SIGINT, on_term);
  dds_qos_t *pqos = dds_create_qos();
  dds_qset_userdata(pqos, "enclave=/;", strlen("enclave=/;"));
  dds_entity_t pp = dds_create_participant((dds_domainid_t)atoi(argv[1]), pqos, NULL);
  dds_delete_qos(pqos);
  if (pp < 0) { fprintf(stderr, "participant: %s\n", dds_strretcode(pp)); return 1; }
  dds_qos_t *services = qos_of(DDS_DURABILITY_VOLATILE, 10), *latched = qos_of(DDS_DURABILITY_TRANSIENT_LOCAL, 1);
  dds_entity_t goal_rd = endpoint(pp, &nav2_msgs_action_dds__NavigateToPose_SendGoal_Request__desc,
                                  "rq/navigate_to_pose/_action/send_goalRequest", services, 0);
  dds_entity_t goal_wr = endpoint(pp, &nav2_msgs_action_dds__NavigateToPose_SendGoal_Response__desc,
                                  "rr/navigate_to_pose/_action/send_goalReply", services, 1);
  dds_entity_t cancel_rd = endpoint(pp, &action_msgs_srv_dds__CancelGoal_Request__desc,
                                    "rq/navigate_to_pose/_action/cancel_goalRequest", services, 0);
  dds_entity_t cancel_wr = endpoint(pp, &action_msgs_srv_dds__CancelGoal_Response__desc,
                                    "rr/navigate_to_pose/_action/cancel_goalReply", services, 1);
  dds_entity_t status_wr = endpoint(pp, &action_msgs_msg_dds__GoalStatusArray__desc,
                                    "rt/navigate_to_pose/_action/status", latched, 1);
  dds_entity_t pose_wr = endpoint(pp, &geometry_msgs_msg_dds__PoseWithCovarianceStamped__desc, "rt/amcl_pose",
                                  latched, 1);
  dds_qos_t *plans = qos_of(DDS_DURABILITY_VOLATILE, 1);
  dds_entity_t plan_wr = endpoint(pp, &nav_msgs_msg_dds__Path__desc, "rt/plan", plans, 1);
  dds_delete_qos(plans);
  dds_delete_qos(services);
  dds_delete_qos(latched);
  printf("{\"ready\": true}\n");
  void *samples[1] = {NULL};
  dds_sample_info_t infos[1];
  char line[256], id[33];
  int commands = 1;
  while (!stop) {
    struct pollfd in = {.fd = 0, .events = POLLIN};
    if (commands && poll(&in, 1, 0) > 0) {
      if (!fgets(line, sizeof line, stdin)) { commands = 0; continue; }
      double x, y, yaw, x1, y1;
      if (sscanf(line, "plan %lf %lf %lf %lf", &x, &y, &x1, &y1) == 4) {
        static geometry_msgs_msg_dds__PoseStamped_ poses[4096];
        uint32_t n = (uint32_t)fmin(4095, ceil(hypot(x1 - x, y1 - y) / 0.05)) + 1;
        memset(poses, 0, sizeof poses);
        for (uint32_t i = 0; i < n; i++) {
          double f = n > 1 ? (double)i / (n - 1) : 0.0;
          poses[i].header.frame_id = "map";
          poses[i].pose.position.x = x + f * (x1 - x);
          poses[i].pose.position.y = y + f * (y1 - y);
          poses[i].pose.orientation.w = 1.0;
        }
        nav_msgs_msg_dds__Path_ path = {.header = {.frame_id = "map"}};
        path.poses._length = path.poses._maximum = n;
        path.poses._buffer = poses;
        dds_write(plan_wr, &path);
      } else if (sscanf(line, "pose %lf %lf %lf", &x, &y, &yaw) == 3) {
        geometry_msgs_msg_dds__PoseWithCovarianceStamped_ p;
        memset(&p, 0, sizeof p);
        p.header.frame_id = "map";
        p.pose.pose.position.x = x;
        p.pose.pose.position.y = y;
        p.pose.pose.orientation.z = sin(yaw / 2);
        p.pose.pose.orientation.w = cos(yaw / 2);
        dds_write(pose_wr, &p);
      } else if (strncmp(line, "succeed", 7) == 0) {
        end_executing(SUCCEEDED);
        publish_status(status_wr);
      }
    }
    dds_return_t n;
    while ((n = dds_take(goal_rd, samples, infos, 1, 1)) > 0) {
      if (infos[0].valid_data) {
        const GoalRequest *r = samples[0];
        const geometry_msgs_msg_dds__Pose_ *p = &r->goal.pose.pose;
        double yaw = 2 * atan2(p->orientation.z, p->orientation.w);
        hex(r->goal_id.uuid, id);
        printf("{\"goal\": \"%s\", \"client\": \"%016llx\", \"seq\": %lld, \"x\": %.4f, \"y\": %.4f, \"yaw\": %.4f, "
               "\"frame_id\": \"%s\"}\n", id, (unsigned long long)r->client, (long long)r->seq,
               p->position.x, p->position.y, yaw, r->goal.pose.header.frame_id);
        GoalReply reply = {.client = r->client, .seq = r->seq, .accepted = true};
        dds_write(goal_wr, &reply);
        end_executing(ABORTED);  /* a new goal preempts: the old one ends ABORTED */
        if (n_goals == MAX_GOALS) { memmove(goals, goals + 1, sizeof goals[0] * (MAX_GOALS - 1)); n_goals--; }
        memset(&goals[n_goals], 0, sizeof goals[0]);
        memcpy(goals[n_goals].goal_info.goal_id.uuid, r->goal_id.uuid, 16);
        goals[n_goals].status = ACCEPTED;
        n_goals++;
        publish_status(status_wr);
        executing = (int)n_goals - 1;
        goals[executing].status = EXECUTING;
        publish_status(status_wr);
      }
      dds_return_loan(goal_rd, samples, n);
      samples[0] = NULL;
    }
    while ((n = dds_take(cancel_rd, samples, infos, 1, 1)) > 0) {
      if (infos[0].valid_data) {
        const CancelRequest *r = samples[0];
        hex(r->goal_info.goal_id.uuid, id);
        printf("{\"cancel\": \"%s\", \"client\": \"%016llx\", \"seq\": %lld}\n", id,
               (unsigned long long)r->client, (long long)r->seq);
        CancelReply reply = {.client = r->client, .seq = r->seq, .return_code = 2 /* ERROR_UNKNOWN_GOAL_ID */};
        action_msgs_msg_dds__GoalInfo_ canceling = r->goal_info;
        for (uint32_t i = 0; i < n_goals; i++) {
          if (memcmp(goals[i].goal_info.goal_id.uuid, r->goal_info.goal_id.uuid, 16) != 0) continue;
          if ((int)i == executing) {
            end_executing(CANCELED);
            reply.return_code = 0; /* ERROR_NONE */
            reply.goals_canceling._length = reply.goals_canceling._maximum = 1;
            reply.goals_canceling._buffer = &canceling;
          } else {
            reply.return_code = 3; /* ERROR_GOAL_TERMINATED */
          }
        }
        dds_write(cancel_wr, &reply);
        publish_status(status_wr);
      }
      dds_return_loan(cancel_rd, samples, n);
      samples[0] = NULL;
    }
    dds_sleepfor(DDS_MSECS(10));
  }
  dds_delete(pp);
  return 0;
}

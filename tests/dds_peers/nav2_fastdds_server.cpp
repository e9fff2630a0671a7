// A stand-in for Nav2's bt_navigator on Debian's Fast DDS 2.9.1 (rmw_fastrtps, Humble's and Jazzy's default
// rmw), for tests/test_ros2_nav2.py: the navigate_to_pose action server as rmw_fastrtps lays a service out on the
// wire. A request is the message's CDR alone; its id is the DATA's sample identity (the request writer's GUID and
// sequence number, as rmw_fastrtps's ServiceListener takes it from SampleInfo::sample_identity, or the client's
// reply reader from related_sample_identity when the client sent one); the reply is the response's CDR alone,
// written with related_sample_identity = that id (as __rmw_send_response does). Types are hand-written
// TopicDataTypes over raw CDR, with no type information sent (as rmw's TypeSupport); the status topic is reliable,
// transient_local, depth 1; the services reliable, volatile, depth 10.
//
// It behaves as nav2_action_server.c does: every goal accepted (ACCEPTED, then EXECUTING), a new goal aborts the
// executing one, a cancel of the executing goal ends it CANCELED, "succeed" on stdin ends it SUCCEEDED, and
// "pose X Y YAW" publishes /amcl_pose. stdout, one JSON line each: {"ready": true}; every goal and cancel taken,
// with the sample identity it was taken under.
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <poll.h>
#include <string>
#include <thread>
#include <vector>

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/common/WriteParams.h>

using namespace eprosima::fastdds::dds;
using eprosima::fastcdr::Cdr;
using eprosima::fastcdr::FastBuffer;
using eprosima::fastrtps::rtps::InstanceHandle_t;
using eprosima::fastrtps::rtps::SerializedPayload_t;

using Raw = std::vector<char>;  // one sample's CDR, encapsulation included

// A type that moves CDR as it is: the program (de)serializes with fastcdr itself.
class RawType : public TopicDataType {
 public:
  explicit RawType(const char *name) {
    setName(name);
    m_typeSize = 8;
    m_isGetKeyDefined = false;
    auto_fill_type_information(false);
    auto_fill_type_object(false);
  }
  bool serialize(void *data, SerializedPayload_t *payload) override {
    Raw *r = static_cast<Raw *>(data);
    if (payload->max_size < r->size()) return false;
    std::memcpy(payload->data, r->data(), r->size());
    payload->length = static_cast<uint32_t>(r->size());
    payload->encapsulation = CDR_LE;
    return true;
  }
  bool deserialize(SerializedPayload_t *payload, void *data) override {
    Raw *r = static_cast<Raw *>(data);
    r->assign(payload->data, payload->data + payload->length);
    return true;
  }
  std::function<uint32_t()> getSerializedSizeProvider(void *data) override {
    return [data] { return static_cast<uint32_t>(static_cast<Raw *>(data)->size()); };
  }
  void *createData() override { return new Raw(); }
  void deleteData(void *data) override { delete static_cast<Raw *>(data); }
  bool getKey(void *, InstanceHandle_t *, bool) override { return false; }
};

enum { UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED };
struct Goal {
  uint8_t uuid[16];
  int8_t status;
};
static std::vector<Goal> goals;
static int executing = -1;
static std::atomic<bool> stop{false};

static std::string hex(const uint8_t *b, size_t n) {
  std::string s;
  char two[3];
  for (size_t i = 0; i < n; i++) {
    std::snprintf(two, sizeof two, "%02x", b[i]);
    s += two;
  }
  return s;
}

// Serializes with `fill` into a little-endian CDR buffer and returns its bytes.
template <class F>
static Raw cdr_of(F fill) {
  static char storage[65536];
  FastBuffer buf(storage, sizeof storage);
  Cdr cdr(buf, Cdr::LITTLE_ENDIANNESS, Cdr::DDS_CDR);
  cdr.serialize_encapsulation();
  fill(cdr);
  return Raw(storage, storage + cdr.getSerializedDataLength());
}

static void publish_status(DataWriter *wr) {
  Raw msg = cdr_of([](Cdr &c) {
    c << static_cast<uint32_t>(goals.size());
    for (const Goal &g : goals) {
      c.serializeArray(g.uuid, 16);
      c << int32_t(0) << uint32_t(0) << g.status;  // stamp, status
    }
  });
  wr->write(&msg);
}

static void end_executing(int8_t status) {
  if (executing >= 0) goals[executing].status = status;
  executing = -1;
}

int main(int argc, char **argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s DOMAIN\n", argv[0]);
    return 2;
  }
  setvbuf(stdout, nullptr, _IOLBF, 0);
  std::signal(SIGTERM, [](int) { stop = true; });
  std::signal(SIGINT, [](int) { stop = true; });
  auto factory = DomainParticipantFactory::get_instance();
  DomainParticipantQos pqos = factory->get_default_participant_qos();
  std::string enclave = "enclave=/;";
  pqos.user_data().setValue(std::vector<eprosima::fastrtps::rtps::octet>(enclave.begin(), enclave.end()));
  pqos.name("wsnav_nav2_fastdds_stand_in");
  DomainParticipant *pp = factory->create_participant(std::atoi(argv[1]), pqos);
  if (!pp) return 1;
  Publisher *pub = pp->create_publisher(PUBLISHER_QOS_DEFAULT);
  Subscriber *sub = pp->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
  auto topic = [pp](const char *name, const char *type) {
    TypeSupport ts(new RawType(type));
    ts.register_type(pp);
    return pp->create_topic(name, type, TOPIC_QOS_DEFAULT);
  };
  auto writer = [pub](Topic *t, bool latched) {
    DataWriterQos q = pub->get_default_datawriter_qos();
    q.endpoint().history_memory_policy = eprosima::fastrtps::rtps::PREALLOCATED_WITH_REALLOC_MEMORY_MODE;
    q.reliability().kind = RELIABLE_RELIABILITY_QOS;
    q.durability().kind = latched ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
    q.history().kind = KEEP_LAST_HISTORY_QOS;
    q.history().depth = latched ? 1 : 10;
    q.data_sharing().off();
    return pub->create_datawriter(t, q);
  };
  auto reader = [sub](Topic *t) {
    DataReaderQos q = sub->get_default_datareader_qos();
    q.endpoint().history_memory_policy = eprosima::fastrtps::rtps::PREALLOCATED_WITH_REALLOC_MEMORY_MODE;
    q.reliability().kind = RELIABLE_RELIABILITY_QOS;
    q.durability().kind = VOLATILE_DURABILITY_QOS;
    q.history().kind = KEEP_LAST_HISTORY_QOS;
    q.history().depth = 10;
    q.data_sharing().off();
    return sub->create_datareader(t, q);
  };
  DataReader *goal_rd = reader(topic("rq/navigate_to_pose/_action/send_goalRequest",
                                     "nav2_msgs::action::dds_::NavigateToPose_SendGoal_Request_"));
  DataWriter *goal_wr = writer(topic("rr/navigate_to_pose/_action/send_goalReply",
                                     "nav2_msgs::action::dds_::NavigateToPose_SendGoal_Response_"), false);
  DataReader *cancel_rd = reader(topic("rq/navigate_to_pose/_action/cancel_goalRequest",
                                       "action_msgs::srv::dds_::CancelGoal_Request_"));
  DataWriter *cancel_wr = writer(topic("rr/navigate_to_pose/_action/cancel_goalReply",
                                       "action_msgs::srv::dds_::CancelGoal_Response_"), false);
  DataWriter *status_wr = writer(topic("rt/navigate_to_pose/_action/status", "action_msgs::msg::dds_::GoalStatusArray_"),
                                 true);
  DataWriter *pose_wr = writer(topic("rt/amcl_pose", "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"), true);
  if (!goal_rd || !goal_wr || !cancel_rd || !cancel_wr || !status_wr || !pose_wr) return 1;
  std::printf("{\"ready\": true}\n");
  Raw raw;
  SampleInfo info;
  char line[256];
  bool commands = true;
  while (!stop) {
    struct pollfd in = {0, POLLIN, 0};
    if (commands && poll(&in, 1, 0) > 0) {
      if (!fgets(line, sizeof line, stdin)) {
        commands = false;
        continue;
      }
      double x, y, yaw;
      if (std::sscanf(line, "pose %lf %lf %lf", &x, &y, &yaw) == 3) {
        Raw msg = cdr_of([&](Cdr &c) {
          c << int32_t(0) << uint32_t(0) << std::string("map");
          c << x << y << 0.0 << 0.0 << 0.0 << std::sin(yaw / 2) << std::cos(yaw / 2);
          for (int i = 0; i < 36; i++) c << 0.0;
        });
        pose_wr->write(&msg);
      } else if (std::strncmp(line, "succeed", 7) == 0) {
        end_executing(SUCCEEDED);
        publish_status(status_wr);
      }
    }
    while (goal_rd->take_next_sample(&raw, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      uint8_t uuid[16];
      int32_t sec;
      uint32_t nsec;
      std::string frame, tree;
      double px, py, pz, qx, qy, qz, qw;
      FastBuffer buf(raw.data(), raw.size());
      Cdr cdr(buf, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
      try {
        cdr.read_encapsulation();
        cdr.deserializeArray(uuid, 16);
        cdr >> sec >> nsec >> frame >> px >> py >> pz >> qx >> qy >> qz >> qw >> tree;
      } catch (...) {
        std::printf("{\"unreadable\": \"goal\", \"length\": %zu}\n", raw.size());
        continue;
      }
      // The request's id, as rmw_fastrtps's ServiceListener takes it.
      eprosima::fastrtps::rtps::SampleIdentity id = info.sample_identity;
      if (info.related_sample_identity.writer_guid() != eprosima::fastrtps::rtps::GUID_t::unknown())
        id.writer_guid() = info.related_sample_identity.writer_guid();
      std::printf("{\"goal\": \"%s\", \"writer\": \"%s\", \"seq\": %llu, \"x\": %.4f, \"y\": %.4f, "
                  "\"yaw\": %.4f, \"frame_id\": \"%s\", \"length\": %zu}\n",
                  hex(uuid, 16).c_str(), hex(id.writer_guid().guidPrefix.value, 12).c_str(),
                  static_cast<unsigned long long>(id.sequence_number().to64long()), px, py,
                  2 * std::atan2(qz, qw), frame.c_str(), raw.size());
      Raw reply = cdr_of([](Cdr &c) { c << true << int32_t(0) << uint32_t(0); });
      eprosima::fastrtps::rtps::WriteParams params;
      params.related_sample_identity(id);
      goal_wr->write(&reply, params);
      end_executing(ABORTED);  // a new goal preempts: the old one ends ABORTED
      if (goals.size() == 64) goals.erase(goals.begin());
      Goal g{};
      std::memcpy(g.uuid, uuid, 16);
      g.status = ACCEPTED;
      goals.push_back(g);
      publish_status(status_wr);
      executing = static_cast<int>(goals.size()) - 1;
      goals[executing].status = EXECUTING;
      publish_status(status_wr);
    }
    while (cancel_rd->take_next_sample(&raw, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      uint8_t uuid[16];
      int32_t sec;
      uint32_t nsec;
      FastBuffer buf(raw.data(), raw.size());
      Cdr cdr(buf, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
      try {
        cdr.read_encapsulation();
        cdr.deserializeArray(uuid, 16);
        cdr >> sec >> nsec;
      } catch (...) {
        std::printf("{\"unreadable\": \"cancel\", \"length\": %zu}\n", raw.size());
        continue;
      }
      std::printf("{\"cancel\": \"%s\", \"length\": %zu}\n", hex(uuid, 16).c_str(), raw.size());
      int8_t code = 2;  // ERROR_UNKNOWN_GOAL_ID
      bool canceling = false;
      for (size_t i = 0; i < goals.size(); i++) {
        if (std::memcmp(goals[i].uuid, uuid, 16) != 0) continue;
        if (static_cast<int>(i) == executing) {
          end_executing(CANCELED);
          code = 0;  // ERROR_NONE
          canceling = true;
        } else {
          code = 3;  // ERROR_GOAL_TERMINATED
        }
      }
      Raw reply = cdr_of([&](Cdr &c) {
        c << code << static_cast<uint32_t>(canceling ? 1 : 0);
        if (canceling) {
          c.serializeArray(uuid, 16);
          c << sec << nsec;
        }
      });
      eprosima::fastrtps::rtps::WriteParams params;
      params.related_sample_identity(info.sample_identity);
      cancel_wr->write(&reply, params);
      publish_status(status_wr);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  pp->delete_contained_entities();
  factory->delete_participant(pp);
  return 0;
}

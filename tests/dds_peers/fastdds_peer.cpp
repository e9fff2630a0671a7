// A Fast DDS 2.9 peer of `wsnav ros2 bridge` (tests/test_ros2_dds_peers.py): Debian's libfastrtps, as ROS 2
// Humble's default rmw (rmw_fastrtps_cpp) uses it. The reader is set up as rmw_fastrtps_cpp sets up a
// subscription's: a TopicDataType of its own (no key, no type object or type information sent: rmw's TypeSupport
// turns both off), the default subscriber, PREALLOCATED_WITH_REALLOC history memory, reliable, transient_local,
// keep-last DEPTH, and a participant with "enclave=/;" user data. ROS_LOCALHOST_ONLY=1 sets the participant's
// transports as Humble's rmw_fastrtps does: UDPv4 on 127.0.0.1 only, and shared memory. One JSON line per
// sample, as cyclone_peer.c.
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastdds/rtps/transport/shared_mem/SharedMemTransportDescriptor.h>

using namespace eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::InstanceHandle_t;
using eprosima::fastrtps::rtps::SerializedPayload_t;

struct Grid {
  std::string frame_id;
  uint32_t width = 0, height = 0;
  std::vector<int8_t> data;
};

class GridType : public TopicDataType {
 public:
  explicit GridType(const char *name) {
    setName(name);
    m_typeSize = 4 + 4;  // as rmw for an unbounded type: the payload grows as needed
    m_isGetKeyDefined = false;
    auto_fill_type_information(false);
    auto_fill_type_object(false);
  }
  bool serialize(void *, SerializedPayload_t *) override { return false; }  // a reader only
  bool deserialize(SerializedPayload_t *payload, void *out) override {
    Grid *g = static_cast<Grid *>(out);
    eprosima::fastcdr::FastBuffer buf(reinterpret_cast<char *>(payload->data), payload->length);
    eprosima::fastcdr::Cdr cdr(buf, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
    try {
      cdr.read_encapsulation();
      int32_t sec;
      uint32_t nsec, len;
      float res;
      double d;
      cdr >> sec >> nsec >> g->frame_id;           // header
      cdr >> sec >> nsec >> res >> g->width >> g->height;  // info up to origin
      for (int i = 0; i < 7; i++) cdr >> d;          // origin: position, orientation
      cdr >> len;
      g->data.resize(len);
      if (len) cdr.deserializeArray(g->data.data(), len);
    } catch (...) {
      return false;
    }
    return true;
  }
  std::function<uint32_t()> getSerializedSizeProvider(void *) override { return [] { return 0u; }; }
  void *createData() override { return new Grid(); }
  void deleteData(void *data) override { delete static_cast<Grid *>(data); }
  bool getKey(void *, InstanceHandle_t *, bool) override { return false; }
};

static std::atomic<bool> stop{false};

int main(int argc, char **argv) {
  if (argc < 4) {
    std::fprintf(stderr, "usage: %s DOMAIN TOPIC DEPTH [SERVICE_TYPE]\n", argv[0]);
    return 2;
  }
  setvbuf(stdout, nullptr, _IOLBF, 0);
  std::signal(SIGTERM, [](int) { stop = true; });
  std::signal(SIGINT, [](int) { stop = true; });
  auto factory = DomainParticipantFactory::get_instance();
  DomainParticipantQos pqos = factory->get_default_participant_qos();
  std::string enclave = "enclave=/;";
  pqos.user_data().setValue(std::vector<eprosima::fastrtps::rtps::octet>(enclave.begin(), enclave.end()));
  pqos.name("wsnav_fastdds_peer");
  const char *localhost_only = std::getenv("ROS_LOCALHOST_ONLY");
  if (localhost_only && std::string(localhost_only) == "1") {
    pqos.transport().use_builtin_transports = false;
    auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
    udp->interfaceWhiteList.emplace_back("127.0.0.1");
    pqos.transport().user_transports.push_back(udp);
    pqos.transport().user_transports.push_back(std::make_shared<eprosima::fastdds::rtps::SharedMemTransportDescriptor>());
  }
  DomainParticipant *pp = factory->create_participant(std::atoi(argv[1]), pqos);
  if (!pp) return 1;
  /* SERVICE_TYPE: a service's request reader as rmw_fastrtps makes one (that type name, volatile) on TOPIC; what
   * it reads is not a grid and is not printed: the test wants it matched, not read. */
  const char *service_type = argc > 4 ? argv[4] : nullptr;
  TypeSupport type(new GridType(service_type ? service_type : "nav_msgs::msg::dds_::OccupancyGrid_"));
  type.register_type(pp);
  Topic *topic = pp->create_topic(argv[2], type.get_type_name(), TOPIC_QOS_DEFAULT);
  Subscriber *sub = pp->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
  DataReaderQos qos = sub->get_default_datareader_qos();
  qos.endpoint().history_memory_policy = eprosima::fastrtps::rtps::PREALLOCATED_WITH_REALLOC_MEMORY_MODE;
  qos.reliability().kind = RELIABLE_RELIABILITY_QOS;
  qos.durability().kind = service_type ? VOLATILE_DURABILITY_QOS : TRANSIENT_LOCAL_DURABILITY_QOS;
  qos.history().kind = KEEP_LAST_HISTORY_QOS;
  qos.history().depth = std::atoi(argv[3]);
  qos.data_sharing().off();
  DataReader *rd = topic && sub ? sub->create_datareader(topic, qos) : nullptr;
  if (!rd) return 1;
  std::printf("{\"ready\": true}\n");
  Grid g;
  SampleInfo info;
  while (!stop) {
    while (rd->take_next_sample(&g, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      uint32_t h = 2166136261u;
      for (int8_t v : g.data) h = (h ^ static_cast<uint8_t>(v)) * 16777619u;
      std::printf("{\"width\": %u, \"height\": %u, \"length\": %zu, \"frame_id\": \"%s\", \"fnv1a\": %u}\n", g.width,
                  g.height, g.data.size(), g.frame_id.c_str(), h);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  pp->delete_contained_entities();
  factory->delete_participant(pp);
  return 0;
}

#include "bench_common.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <thread>

namespace hapticd::bench {

Machine describe_machine() {
  Machine m;
  std::ifstream cpuinfo("/proc/cpuinfo");
  for (std::string line; std::getline(cpuinfo, line);) {
    if (line.rfind("model name", 0) == 0) {
      m.cpu = line.substr(line.find(':') + 2);
      break;
    }
  }
  m.cores = static_cast<int>(std::thread::hardware_concurrency());
  // The BLAS CHOLMOD calls is whichever libblas the loader mapped (Debian alternatives).
  std::ifstream maps("/proc/self/maps");
  for (std::string line; std::getline(maps, line);) {
    const auto slash = line.find('/');
    if (slash == std::string::npos) continue;
    const std::string path = line.substr(slash);
    if (path.find("libblas") != std::string::npos || path.find("libopenblas") != std::string::npos) {
      m.blas = path;
      break;
    }
  }
  if (FILE* p = popen("git rev-parse --short HEAD 2>/dev/null", "r")) {
    char buf[64] = {0};
    if (std::fgets(buf, sizeof buf, p)) m.git_revision = std::string(buf, strcspn(buf, "\n"));
    pclose(p);
  }
  return m;
}

nlohmann::json to_json(const Machine& m) {
  return {{"cpu", m.cpu}, {"cores", m.cores}, {"blas", m.blas}, {"git_revision", m.git_revision}};
}

void write_json(const std::string& path, const nlohmann::json& doc) {
  std::ofstream out(path);
  if (!out) throw std::runtime_error("cannot write " + path);
  out << doc.dump(2) << "\n";
  if (!out) throw std::runtime_error("failed writing " + path);
}

std::filesystem::path own_directory() { return std::filesystem::read_symlink("/proc/self/exe").parent_path(); }

protocol::Hello stylus_hello(const std::string& client_name, unsigned rate_hz) {
  protocol::Hello h;
  h.client_name.assign(client_name);
  h.device_kind = protocol::DeviceKind::kStylus;
  protocol::TrackedFrame f;
  f.id = 0;
  f.dof = 6;
  f.name = "stylus";
  h.frames.push_back(f);
  h.requested_rate_hz = rate_hz;
  return h;
}

}  // namespace hapticd::bench

#!/usr/bin/env bash
# End to end on loopback: hapticd on the stylus scene and haptic-device pressing
# and stroking for a few seconds. Asserts the issue's loose bounds (a shared
# machine; haptic-bench latency holds the real targets): no loss, late replies
# under 5 %, RTT p99 under 5 ms, forces within the device limit, contact with
# the bunny, no resets, and a rendering that put no net energy into the device.
# The scene (stylus_static_bunny.json) is the stylus scene with the bunny
# static: the shipped scene's rigid bunny rests on one vertex, and tipping it
# under the stylus releases its potential energy (a few mJ) into the device,
# which no passive rendering may prevent; the bound is the rendering's alone.
# A run in which the simulated device itself missed more than 2 % of its ticks
# measured the machine, not the server: its timing bounds (late replies, RTT)
# are not judged and the run is repeated, up to three runs; every other bound
# holds on every run.
# With COMPETITORS (by hand, not in make test: a loaded machine, issue 17), that many CPU-bound
# processes run at nice -10 beside the server, and the simulated device's servo loop runs at real-time
# priority where permitted (as a device driver's), so that the server, not the device, is starved.
# Usage: stylus_loopback.sh BIN_DIR SCENE [SECONDS [COMPETITORS]]
set -euo pipefail
bin=$1
scene=$2
seconds=${3:-3}
competitors=${4:-0}
work=$(mktemp -d)
server_pid=""
busy_pids=()
trap 'kill "$server_pid" "${busy_pids[@]}" 2>/dev/null || true; rm -rf "$work"' EXIT
source "$(dirname "$0")/lib.sh"
device_priority=()
if [ "$competitors" -gt 0 ]; then set_device_priority; fi
for _ in $(seq 1 "$competitors"); do
  nice -n -10 bash -c 'while :; do :; done' &
  busy_pids+=($!)
done

# One run; exits 0 if it passes, 1 if it fails, 3 if it passed every bound but timing while the
# device was starved (the caller repeats it).
run_once() {
  rm -f "$work"/*
  start_hapticd "$bin" "$scene" "$seconds" "$work"
  "${device_priority[@]}" "$bin/haptic-device" --server "127.0.0.1:$port" --device stylus --trajectory press-stroke --rate 1000 \
    --duration "$seconds" --report "$work/device.json" || return 1
  kill -INT "$server_pid"
  local server_status=0
  wait "$server_pid" || server_status=$?
  server_pid=""
  if [ "$server_status" -ne 0 ]; then echo "FAILED: hapticd exited with status $server_status"; return 1; fi
  python3 - "$work/device.json" "$work/server.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
s = json.load(open(sys.argv[2]))
missed = d["missed_ticks"] / max(1, d["ticks"])
print(f"rtt p50 {d['rtt_us']['p50']:.0f} us, p99 {d['rtt_us']['p99']:.0f} us; late {100 * d['late_fraction']:.2f} %, "
      f"loss {100 * d['loss_fraction']:.2f} %; force max {d['force_n']['max']:.2f} N; "
      f"passivity {d['passivity_energy_j']:.2e} J; contact {100 * d.get('contact_fraction', 0):.0f} %; "
      f"server replies {s['replies']}, visual {s['visual']['rate_hz_achieved']:.1f} Hz; device missed {100 * missed:.2f} % of its ticks")
ss = d.get("server_stats") or {}
if ss:
    print(f"server's passivity observer: the device did {ss['passivity_energy_j']:+.2e} J on the rendering; "
          f"the controller took back {ss['passivity_damped_j']:.2e} J in {ss['passivity_actions']} replies")
failures, timing = [], []
if d["loss_fraction"] != 0: failures.append(f"loss {d['loss_fraction']}")
# Late replies follow the shared VM's scheduling (0-2.3 % seen in fresh-clone CI runs, most of it the
# client's own missed ticks); 5 % still catches a server that stalls.
if not d["late_fraction"] < 0.05: timing.append(f"late fraction {d['late_fraction']}")
if not d["rtt_us"]["p99"] < 5000: timing.append(f"rtt p99 {d['rtt_us']['p99']} us")
if not d["force_n"]["max"] <= 8.0 + 1e-3: failures.append(f"force max {d['force_n']['max']} N over the 8 N limit")
if s["replies"] < d["samples_sent"]: failures.append(f"server replied {s['replies']} of {d['samples_sent']}")
if not d["passivity_energy_j"] <= 0: failures.append(f"the rendering put {d['passivity_energy_j']} J into the device")
if not d.get("contact_fraction", 0) > 0.2: failures.append("the stylus never pressed on the bunny")
if s["proxy_resets"] or s["visual"]["hand_resets"]: failures.append("resets")
if failures or (timing and missed <= 0.02):
    print("FAILED: " + "; ".join(failures + timing)); sys.exit(1)
if timing:
    print(f"STARVED: the device missed {100 * missed:.2f} % of its ticks; not judged: " + "; ".join(timing)); sys.exit(3)
PY
}

for attempt in 1 2 3; do
  status=0
  run_once || status=$?
  [ "$status" -ne 3 ] && exit "$status"
done
echo "FAILED: the machine starved the device in 3 of 3 runs"
exit 1

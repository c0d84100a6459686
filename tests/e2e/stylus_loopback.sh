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
# Usage: stylus_loopback.sh BIN_DIR SCENE [SECONDS]
set -euo pipefail
bin=$1
scene=$2
seconds=${3:-3}
work=$(mktemp -d)
server_pid=""
trap 'kill "$server_pid" 2>/dev/null || true; rm -rf "$work"' EXIT
source "$(dirname "$0")/lib.sh"
start_hapticd "$bin" "$scene" "$seconds" "$work"

"$bin/haptic-device" --server "127.0.0.1:$port" --device stylus --trajectory press-stroke --rate 1000 \
  --duration "$seconds" --report "$work/device.json"
kill -INT "$server_pid"
wait "$server_pid"

python3 - "$work/device.json" "$work/server.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
s = json.load(open(sys.argv[2]))
print(f"rtt p50 {d['rtt_us']['p50']:.0f} us, p99 {d['rtt_us']['p99']:.0f} us; late {100 * d['late_fraction']:.2f} %, "
      f"loss {100 * d['loss_fraction']:.2f} %; force max {d['force_n']['max']:.2f} N; "
      f"passivity {d['passivity_energy_j']:.2e} J; contact {100 * d.get('contact_fraction', 0):.0f} %; "
      f"server replies {s['replies']}, visual {s['visual']['rate_hz_achieved']:.1f} Hz")
failures = []
if d["loss_fraction"] != 0: failures.append(f"loss {d['loss_fraction']}")
# Late replies follow the shared VM's scheduling (0-2.3 % seen in fresh-clone CI runs, most of it the
# client's own missed ticks); 5 % still catches a server that stalls.
if not d["late_fraction"] < 0.05: failures.append(f"late fraction {d['late_fraction']}")
if not d["rtt_us"]["p99"] < 5000: failures.append(f"rtt p99 {d['rtt_us']['p99']} us")
if not d["force_n"]["max"] <= 8.0 + 1e-3: failures.append(f"force max {d['force_n']['max']} N over the 8 N limit")
if s["replies"] < d["samples_sent"]: failures.append(f"server replied {s['replies']} of {d['samples_sent']}")
if not d["passivity_energy_j"] <= 0: failures.append(f"the rendering put {d['passivity_energy_j']} J into the device")
if not d.get("contact_fraction", 0) > 0.2: failures.append("the stylus never pressed on the bunny")
if s["proxy_resets"] or s["visual"]["hand_resets"]: failures.append("resets")
if failures:
    print("FAILED: " + "; ".join(failures)); sys.exit(1)
PY

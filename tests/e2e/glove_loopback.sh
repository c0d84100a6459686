#!/usr/bin/env bash
# End to end on loopback: hapticd on the glove scene and a simulated 16-frame
# glove closing into a power grasp over the box. Asserts: no loss, every pose
# answered, no reset, the grasp touches the box with at least three fingers,
# the palm (which touches nothing) gets no force, no frame's force exceeds
# the device limit, and, with hapticd's visual loop at 14 Hz or more (below),
# the rendering put no energy into the glove (issue 17;
# the work of the replies on its palm and joints, which the glove's own
# simulation books: the run ends pressing into the box, so what the coupling
# holds stretched then is on the glove's side of the account).
# BUSY=1: a CPU-bound process competes for one of the two cores all the while (a loaded machine:
# hapticd's visual loop then steps the FEM hand at 13-15 Hz instead of 16-20, its models late).
# Usage: [BUSY=1] glove_loopback.sh BIN_DIR SCENE [SECONDS]
set -euo pipefail
bin=$1
scene=$2
seconds=${3:-4}
work=$(mktemp -d)
server_pid=""
busy_pid=""
trap 'kill "$server_pid" $busy_pid 2>/dev/null || true; rm -rf "$work"' EXIT
source "$(dirname "$0")/lib.sh"
if [ "${BUSY:-0}" = 1 ]; then
  bash -c 'while :; do :; done' &
  busy_pid=$!
fi
start_hapticd "$bin" "$scene" "$seconds" "$work"

set_device_priority
"${device_priority[@]}" "$bin/haptic-device" --server "127.0.0.1:$port" --device glove --frames 16 --trajectory grasp --rate 1000 \
  --duration "$seconds" --report "$work/device.json" --trace "$work/trace.csv"
kill -INT "$server_pid"
wait "$server_pid"

python3 - "$work/device.json" "$work/server.json" "$work/trace.csv" <<'PY'
import csv, json, math, os, sys
d = json.load(open(sys.argv[1]))
s = json.load(open(sys.argv[2]))
fingers = d["fingers"]
touching = [f for f, v in fingers.items() if v["contact_fraction"] > 0]
limit = d["welcome"]["force_limit_n"]
print(f"loss {100 * d['loss_fraction']:.2f} %, late {100 * d['late_fraction']:.2f} %; fingers touching: {touching}; "
      f"palm contact {100 * d['palm']['contact_fraction']:.0f} %; resets {s['proxy_resets']} + {s['visual']['hand_resets']}; passivity {d['passivity_energy_j']:.3f} J; "
      f"visual {s['visual']['rate_hz_achieved']:.1f} Hz")
failures = []
if d["loss_fraction"] != 0: failures.append(f"loss {d['loss_fraction']}")
if s["replies"] < d["samples_sent"]: failures.append(f"server replied {s['replies']} of {d['samples_sent']}")
# A reset is the safety response to a fault (state back on the device, force zeroed): a run with
# one has diverged, and fails.
resets = s["proxy_resets"] + s["visual"]["hand_resets"]
if resets > 0:
    failures.append(f"resets: proxy {s['proxy_resets']}, hand {s['visual']['hand_resets']}")
if len(touching) < 3: failures.append(f"only {touching} touched the box")
for name, part in list(fingers.items()) + [("palm", d["palm"])]:
    if part["contact_fraction"] == 0 and part["force_n"]["max"] > 0.05:
        failures.append(f"the {name} touched nothing but felt {part['force_n']['max']} N")
worst = 0.0
with open(sys.argv[3]) as f:
    rows = csv.DictReader(f)
    cols = [c[: -len("_x_n")] for c in rows.fieldnames if c.startswith("f_") and c.endswith("_x_n")]
    for row in rows:
        for base in cols:
            worst = max(worst, math.sqrt(sum(float(row[base + a]) ** 2 for a in ("_x_n", "_y_n", "_z_n"))))
if not cols: failures.append("the trace has no per-frame forces")
if worst > limit + 1e-3: failures.append(f"a frame felt {worst} N over the {limit} N limit")
# The bound is asserted where the lockstep runner's held press is passive and comes to rest with its
# models late as a busy machine delivers them: a visual loop at 14 Hz and up (GloveLateModels/
# GlovePressHold, 14 and 16 Hz). Below, the lockstep runner's hold ends passive down to 8 Hz since the
# tick's stiffness is made passive (SlowVisualLoop/GlovePressHold; at 12 Hz it gained +0.024 J before,
# and a loaded host ran this busy run at 9.3 Hz once and it gave +0.028 J), but some of those holds
# still swing (Issue17KnownFault/GlovePressHold), and through this server it is not measured yet
# there: reported, not asserted. Under a sanitizer (the asan and tsan
# presets set these) the FEM hand steps several times slower: left to the Release run.
rate = s["visual"]["rate_hz_achieved"]
if any(k in os.environ for k in ("ASAN_OPTIONS", "TSAN_OPTIONS")):
    print("instrumented build: the passivity check is left to the Release run")
elif rate < 14:
    print(f"visual loop at {rate:.1f} Hz, below 14 Hz (issue 17): passivity not asserted")
elif d["passivity_energy_j"] > 0:
    failures.append(f"the rendering put {d['passivity_energy_j']} J into the glove")
if failures:
    print("FAILED: " + "; ".join(failures)); sys.exit(1)
PY

#!/usr/bin/env bash
# End to end through the chaos relay, authenticated: hapticd with a fresh key on the stylus scene,
# haptic-chaos in front of it, and haptic-device with the same key pressing and stroking through
# the relay. MODE faults (the issue's run): 10 % loss, 5 % reorder, 1 % duplication and 1 ms jitter
# each way. MODE corrupt: 1 % of the datagrams each way with one byte changed.
# Asserts: no force above the Welcome's limit, no force change faster than its rate limit, the
# session alive to the end, no net energy into the device (passivity), no resets; faults: every
# duplicate the relay made refused as a replay by hapticd and by the client, and nothing else
# refused; corrupt: every corrupted datagram refused by its MAC, and nothing else refused.
# MODE stalls (not in ctest: a known fault, see the README's Known limits): faults, and hapticd
# stopped (SIGSTOP) for 50 ms every 300 ms, as a machine too busy to run it would.
# Usage: chaos_loopback.sh BIN_DIR SCENE [SECONDS [MODE]]
set -euo pipefail
bin=$1
scene=$2
seconds=${3:-20}
mode=${4:-faults}
work=$(mktemp -d)
server_pid=""
chaos_pid=""
stall_pid=""
trap 'kill "$stall_pid" 2>/dev/null || true; kill -CONT "$server_pid" 2>/dev/null || true; kill "$chaos_pid" "$server_pid" 2>/dev/null || true; rm -rf "$work"' EXIT
source "$(dirname "$0")/lib.sh"

"$bin/hapticd" --generate-key "$work/key" > /dev/null
start_hapticd "$bin" "$scene" "$seconds" "$work" --key-file "$work/key"
case "$mode" in
  faults | stalls) faults=(--loss 0.1 --reorder 0.05 --duplicate 0.01 --jitter-ms 1) ;;
  corrupt) faults=(--corrupt 0.01) ;;
  *) echo "unknown mode $mode"; exit 2 ;;
esac
"$bin/haptic-chaos" --listen 0 --forward "127.0.0.1:$port" "${faults[@]}" --seed 7 --counts "$work/chaos.json" \
  > "$work/chaos.out" 2> "$work/chaos.err" &
chaos_pid=$!
chaos_port=""
for _ in $(seq 1 200); do
  chaos_port=$(sed -n 's/^haptic-chaos listening on [0-9.]*:\([0-9]*\)$/\1/p' "$work/chaos.out" 2>/dev/null || true)
  [ -n "$chaos_port" ] && break
  sleep 0.05
done
[ -n "$chaos_port" ] || { echo "haptic-chaos did not listen:"; cat "$work/chaos.err"; exit 1; }
if [ "$mode" = stalls ]; then
  (while kill -0 "$server_pid" 2>/dev/null; do
     sleep 0.25; kill -STOP "$server_pid" 2>/dev/null || break; sleep 0.05; kill -CONT "$server_pid" 2>/dev/null || break
   done) &
  stall_pid=$!
fi

"$bin/haptic-device" --server "127.0.0.1:$chaos_port" --key-file "$work/key" --device stylus \
  --trajectory press-stroke --rate 1000 --duration "$seconds" --handshake-timeout 5 --report "$work/device.json"
if [ -n "$stall_pid" ]; then kill "$stall_pid"; wait "$stall_pid" 2>/dev/null || true; kill -CONT "$server_pid"; fi
kill -INT "$chaos_pid"
wait "$chaos_pid"
kill -INT "$server_pid"
wait "$server_pid"

python3 - "$work/device.json" "$work/server.json" "$work/chaos.json" "$mode" <<'PY'
import json, os, sys
d = json.load(open(sys.argv[1]))
s = json.load(open(sys.argv[2]))
c = json.load(open(sys.argv[3]))
mode = sys.argv[4]
w = d["welcome"]
rejected = s["packets"]["rejected"]
client = d["client"]
up, down = c["to_server"], c["to_client"]
print(f"{mode}: relay to server {up}\n{mode}: relay to client {down}")
print(f"{mode}: sent {d['samples_sent']}, replies {d['replies']} (loss {100 * d['loss_fraction']:.1f} %); "
      f"force max {d['force_n']['max']:.2f} N (limit {w['force_limit_n']}); rate max {d['force_rate_max_n_per_s']:.0f} N/s "
      f"(limit {w['max_force_rate_n_per_s']}); passivity {d['passivity_energy_j']:.3e} J; "
      f"contact {100 * d['contact_fraction']:.0f} %; hapticd rejected {rejected}, stale {s['packets']['stale']}; "
      f"client unauthenticated {client['datagrams_unauthenticated']}, rejected {client['datagrams_rejected']}")
failures = []
if not d["force_n"]["max"] <= w["force_limit_n"] + 1e-3: failures.append("force above the limit")
# Under a sanitizer (the asan and tsan presets set these) the world steps several times slower, so
# the models come late and the checks that need a Release visual rate (no force step past the rate
# limit: a proxy reset zeroes the force at once; passivity; no reset) are the Release run's; this
# run is there for memory and threading errors, and for the MAC and replay counts below.
instrumented = any(k in os.environ for k in ("ASAN_OPTIONS", "TSAN_OPTIONS"))
if instrumented:
    print(f"{mode}: instrumented build: rate limit, passivity and reset checks left to the Release run")
else:
    # float32 forces over >= 0.1 ms: rounding is far below 1 N/s.
    if not d["force_rate_max_n_per_s"] <= w["max_force_rate_n_per_s"] + 1.0: failures.append("force rate above the limit")
    if not d["passivity_energy_j"] <= 0: failures.append(f"the rendering put {d['passivity_energy_j']} J into the device")
    if s["proxy_resets"] or s["visual"]["hand_resets"]: failures.append("resets")
if s["sessions"]["opened"] != 1 or s["sessions"]["timed_out"] != 0: failures.append(f"sessions {s['sessions']}")
if d["server_stats"] is not None and d["server_stats"]["sessions_active"] != 1: failures.append("session not alive")
if not d["contact_fraction"] > 0.2: failures.append("the stylus never pressed on the bunny")
if s["packets"]["in"] != up["sent"]: failures.append(f"hapticd read {s['packets']['in']} of {up['sent']} datagrams")
if mode in ("faults", "stalls"):
    # Both ways ~10 % lost and ~5 % overtaken (dropped as stale): ~28 % of the poses unanswered
    # (~40 % with the stalls: a queue read at once is answered at once, and overtaken).
    if mode == "faults" and not 0.15 < d["loss_fraction"] < 0.4: failures.append(f"loss fraction {d['loss_fraction']}")
    if rejected != ({"replayed": up["duplicated"]} if up["duplicated"] else {}):
        failures.append(f"hapticd refused {rejected}, the relay duplicated {up['duplicated']}")
    if client["datagrams_unauthenticated"] != down["duplicated"]:
        failures.append(f"the client refused {client['datagrams_unauthenticated']}, the relay duplicated {down['duplicated']}")
else:
    auth = sum(rejected.get(r, 0) for r in ("missing_mac", "bad_mac", "unknown_session"))
    if auth != up["corrupted"] or sum(rejected.values()) != auth:
        failures.append(f"hapticd refused {rejected}, the relay corrupted {up['corrupted']}")
    refused = client["datagrams_unauthenticated"] + client["datagrams_rejected"]
    # A corrupted Hello may draw a plain Error the client refuses too.
    if not down["corrupted"] <= refused <= down["corrupted"] + 3:
        failures.append(f"the client refused {refused}, the relay corrupted {down['corrupted']}")
if failures:
    print("FAILED: " + "; ".join(failures)); sys.exit(1)
PY

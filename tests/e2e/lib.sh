# Shared by the end-to-end scripts: start_hapticd BIN SCENE SECONDS WORKDIR [HAPTICD_ARGS...]
# starts hapticd on a free loopback port for SECONDS + 20 s, writing its stats to
# WORKDIR/server.json, and sets server_pid and port (exits 1 if it never listens).
start_hapticd() {
  local bin=$1 scene=$2 seconds=$3 work=$4
  "$bin/hapticd" --scene "$scene" --port 0 --duration $((seconds + 20)) --stats "$work/server.json" "${@:5}" \
    > "$work/server.out" 2> "$work/server.err" &
  server_pid=$!
  port=""
  # Up to 60 s: under ASan hapticd takes ~27 s to build the stylus scene (the hand's flesh query for
  # the bunny's vertices, ~0.8 s in Release).
  for _ in $(seq 1 1200); do
    port=$(sed -n 's/^hapticd listening on [0-9.]*:\([0-9]*\)$/\1/p' "$work/server.out" 2>/dev/null || true)
    [ -n "$port" ] && return 0
    if ! kill -0 "$server_pid" 2>/dev/null; then
      echo "hapticd exited before listening:"; cat "$work/server.err"; exit 1
    fi
    sleep 0.05
  done
  echo "hapticd did not print its port within 60 s"; exit 1
}

# set_device_priority: sets device_priority to the command prefix that runs a simulated device's
# servo loop at real-time priority where that is permitted, as a real device's driver runs (empty
# where it is not, or with DEVICE_REALTIME=0): the load a test puts on the machine is the server's.
set_device_priority() {
  device_priority=()
  if [ "${DEVICE_REALTIME:-1}" != 0 ] && chrt -f 20 true 2>/dev/null; then device_priority=(chrt -f 20); fi
}

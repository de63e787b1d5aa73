#!/usr/bin/env bash
# The VE on another host: ve_sim in a network namespace of its own, the rest of the graph
# (device_driver hosting lmi_controller, recorder, the bringup) in a second one, joined by a
# link with one-way delay, uniform jitter and random loss in a third namespace:
#
#   ${P}lab: lab0 10.77.0.1/24 == veth == llab [${P}link: link stage] lve == veth == ve0 10.77.0.2/24 :${P}ve
#
# Link stage: the kernel's netem qdisc where it exists (a Linux bridge br0 over llab and lve,
# `netem delay D J loss L` on the egress of both), else the user-space layer-2 bridge
# haptic_topology/net/delay_bridge.py (AF_PACKET; delay, jitter and loss per frame, seeded;
# counters in link.json). These machines have no netem ("Specified qdisc kind is unknown").
# HT_LINK=bridge forces the bridge, HT_LINK=netem requires netem.
#
# DDS goes over the link as between two machines: ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET
# (multicast discovery through the link), the same ROS_DOMAIN_ID on both sides, and the Fast
# DDS profile config/fastdds_two_hosts.xml (UDPv4 only, no shared memory, as the project's
# loopback profile; reliable writers' heartbeat every 20 ms, so a lost datagram is repaired
# within a heartbeat and a round trip instead of holding a reliable topic for seconds).
# HT_DDS_PROFILE=default: Fast DDS's defaults instead, with FASTDDS_BUILTIN_TRANSPORTS=UDPv4.
#
# usage (root needed: ip netns, veth, packet sockets):
#   scripts/two_hosts.sh check              exit 0 if this machine can do it, else 1 + reason
#   scripts/two_hosts.sh up DELAY_MS        namespaces and link stage (leaves them up)
#   scripts/two_hosts.sh down               stop the link stage, write link.json, delete all
#   scripts/two_hosts.sh run SCENARIO DELAY_MS [haptic-topology run options ...]
#       up, `haptic-topology run SCENARIO` in ${P}lab with ve_sim in ${P}ve
#       (--node-prefix 've_sim=ip netns exec ${P}ve'), down; always tears down (trap; after
#       a Ctrl-C once `haptic-topology run` has returned).
#       The bag goes to $OUT (default bags/two_hosts_<scenario>_<delay>ms_<time>), with the
#       link stage's counters in <bag>/link.json.
#   scripts/two_hosts.sh run-device SCENARIO DELAY_MS [haptic-topology run options ...]
#       the device on the far side instead (issue 15, item 3): up, `haptic-topology
#       device-server --scenario SCENARIO` on ${P}ve (10.77.0.2, port $HT_DEVICE_PORT),
#       `haptic-topology run SCENARIO` with the whole graph (ve_sim included) in ${P}lab and
#       device_driver's `backend: network` pointed at the server (params: a copy of
#       $HT_PARAMS with backend and backend_options set; do not pass --params), the server
#       stopped, down. DDS stays inside ${P}lab (the environment's setup, as a plain `run`;
#       HT_DDS_PROFILE does not apply). Bag to $OUT (default
#       bags/two_hosts_device_<scenario>_<delay>ms_<time>), plus link.json,
#       device_server.json (the server's counters), device_server.log,
#       device_server_log.csv (the wrench it applied, per cycle) and device_server_cpu.json
#       (its CPU time). The link is authenticated with a new key (HT_DEVICE_KEY); with
#       HT_FORGER=1 a forger in ${P}lab sends forged and replayed commands (forger.json).
#   scripts/two_hosts.sh exec lab|ve CMD ...  a command in a namespace, with the DDS setup
# Without root, every command except `check` prints one line saying it needs root and exits
# 0 (skipped), so an unprivileged CI job passes; `check` exits 1.
#
# Environment: HT_PREFIX (namespace prefix P, default ht_; the test suite uses a unique one),
# HT_JITTER (fraction, 0.2), HT_LOSS (probability, 0.01), HT_SEED (1), HT_BRIDGE_PRIORITY
# (SCHED_FIFO priority of delay_bridge, 10; 0: normal scheduling), HT_LINK
# (auto|bridge|netem), HT_DDS_PROFILE (two_hosts|default), HT_STATE (state dir, default
# /tmp/two_hosts_<P>), OUT, ROS_DOMAIN_ID
# (default 0: the namespaces are a network of their own), HAPTIC_VENV (default .venv);
# run-device: HT_DEVICE_PORT (47001), HT_DEVICE_OPTIONS (more backend_options, e.g.
# 'stale_ms: 20'), HT_DEVICE_PRIORITY (SCHED_FIFO priority of the server, 0: normal),
# HT_PARAMS (params file to copy, default config/haptic_topology.yaml), HT_DEVICE_KEY (the
# link's key file; default: a new one in the state dir; `none`: an unauthenticated link
# with --trusted-network), HT_FORGER (1: scripts/link_forger.py runs in ${P}lab during the
# run, forging commands to the device; its counts go to forger.json).
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=${HAPTIC_VENV:-$REPO/.venv}
PY=$VENV/bin/python
P=${HT_PREFIX:-ht_}
NS_LAB=${P}lab
NS_VE=${P}ve
NS_LINK=${P}link
JITTER=${HT_JITTER:-0.2}
LOSS=${HT_LOSS:-0.01}
SEED=${HT_SEED:-1}
LINK=${HT_LINK:-auto}
STATE=${HT_STATE:-/tmp/two_hosts_${P%_}}
LAB_IP=10.77.0.1
VE_IP=10.77.0.2
PROG=two_hosts.sh

die() { echo "$PROG: error: $*" >&2; exit 2; }

# The DDS setup of both sides (as on two machines; see the header), put before a command.
DDS_ENV=(env -u FASTRTPS_DEFAULT_PROFILES_FILE -u FASTDDS_BUILTIN_TRANSPORTS
         -u ROS_LOCALHOST_ONLY -u ROS_STATIC_PEERS ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET
         "ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-0}" RMW_IMPLEMENTATION=rmw_fastrtps_cpp)
case ${HT_DDS_PROFILE:-two_hosts} in
    two_hosts) DDS_ENV+=("FASTRTPS_DEFAULT_PROFILES_FILE=$REPO/config/fastdds_two_hosts.xml") ;;
    default) DDS_ENV+=(FASTDDS_BUILTIN_TRANSPORTS=UDPv4) ;;
    *) echo "$PROG: error: HT_DDS_PROFILE must be two_hosts or default" >&2; exit 2 ;;
esac

# Why this machine cannot run it (empty: it can).
why_not() {
    if [[ $(id -u) -ne 0 ]]; then echo "needs root (ip netns, veth, packet sockets)"; return; fi
    command -v ip >/dev/null || { echo "no 'ip' command (iproute2)"; return; }
    local probe=${P}probe$$
    if ! ip netns add "$probe" 2>/dev/null; then echo "cannot create a network namespace"; return; fi
    if ! ip -n "$probe" link add p0 type veth peer name p1 2>/dev/null; then
        ip netns del "$probe"; echo "no veth support"; return
    fi
    ip netns del "$probe"
    [[ -x $PY ]] || echo "no venv python at $PY (make setup)"
}

skip_unless_root() {
    if [[ $(id -u) -ne 0 ]]; then
        echo "$PROG: skipped: needs root (ip netns, veth, packet sockets); run it with sudo"
        exit 0
    fi
}

ns_exists() { ip netns list | awk '{print $1}' | grep -qx "$1"; }

netem_works() {
    ip netns exec "$NS_LINK" tc qdisc add dev llab root netem delay 1ms 2>/dev/null || return 1
    ip netns exec "$NS_LINK" tc qdisc del dev llab root 2>/dev/null || true
}

cmd_up() {
    local delay_ms=${1:?usage: $PROG up DELAY_MS}
    [[ $delay_ms =~ ^[0-9]+([.][0-9]+)?$ ]] || die "DELAY_MS must be a number of ms, got '$delay_ms'"
    for ns in "$NS_LAB" "$NS_VE" "$NS_LINK"; do
        ns_exists "$ns" && die "namespace $ns exists already ($PROG down, or another HT_PREFIX)"
    done
    mkdir -p "$STATE"
    rm -f "$STATE/link.json" "$STATE/bridge.pid"
    for ns in "$NS_LAB" "$NS_VE" "$NS_LINK"; do
        ip netns add "$ns"
        ip -n "$ns" link set lo up
        # IPv4 only: no router solicitations or MLD reports crossing the link.
        ip netns exec "$ns" sysctl -qw net.ipv6.conf.all.disable_ipv6=1 \
            net.ipv6.conf.default.disable_ipv6=1
    done
    ip -n "$NS_LINK" link add llab type veth peer name lab0 netns "$NS_LAB"
    ip -n "$NS_LINK" link add lve type veth peer name ve0 netns "$NS_VE"
    local ns dev ipaddr
    for spec in "$NS_LAB lab0 $LAB_IP" "$NS_VE ve0 $VE_IP"; do
        read -r ns dev ipaddr <<<"$spec"
        ip -n "$ns" addr add "$ipaddr/24" dev "$dev"
        ip -n "$ns" link set "$dev" up multicast on
        # DDS discovery multicast (239.255.0.1) leaves through the link.
        ip -n "$ns" route add 224.0.0.0/4 dev "$dev"
    done
    ip -n "$NS_LINK" link set llab up promisc on
    ip -n "$NS_LINK" link set lve up promisc on
    local jitter_ms
    jitter_ms=$(awk -v d="$delay_ms" -v j="$JITTER" 'BEGIN { printf "%.3f", d * j }')
    local loss_pct
    loss_pct=$(awk -v l="$LOSS" 'BEGIN { printf "%.4f", l * 100 }')
    local use=$LINK
    if [[ $use == auto ]]; then
        if netem_works; then use=netem; else use=bridge; fi
    fi
    if [[ $use == netem ]]; then
        netem_works || die "HT_LINK=netem: this kernel has no netem qdisc"
        ip -n "$NS_LINK" link add br0 type bridge
        ip -n "$NS_LINK" link set llab master br0
        ip -n "$NS_LINK" link set lve master br0
        ip -n "$NS_LINK" link set br0 up
        local spec=()
        if awk -v d="$delay_ms" 'BEGIN { exit !(d > 0) }'; then
            spec=(delay "${delay_ms}ms" "${jitter_ms}ms")
        fi
        for dev in llab lve; do
            ip netns exec "$NS_LINK" tc qdisc add dev "$dev" root netem "${spec[@]}" \
                loss "${loss_pct}%"
        done
        printf '{"stage": "netem", "state": "running", "delay_ms": %s, "jitter": %s, "loss": %s}\n' \
            "$delay_ms" "$JITTER" "$LOSS" >"$STATE/link.json"
    elif [[ $use == bridge ]]; then
        # Its own session: a Ctrl-C meant for the run must not cut the link under it (the
        # bridge is stopped by `down`, after the run).
        setsid ip netns exec "$NS_LINK" "$PY" -m haptic_topology.net.delay_bridge --a llab --b lve \
            --delay-ms "$delay_ms" --jitter "$JITTER" --loss "$LOSS" --seed "$SEED" \
            --stats "$STATE/link.json" --rt-priority "${HT_BRIDGE_PRIORITY:-10}" \
            >"$STATE/bridge.log" 2>&1 &
        echo $! >"$STATE/bridge.pid"
        # The bridge writes link.json once its sockets are bound.
        local i
        for i in $(seq 100); do
            [[ -s $STATE/link.json ]] && break
            kill -0 "$(cat "$STATE/bridge.pid")" 2>/dev/null \
                || die "delay_bridge exited: $(tail -n 3 "$STATE/bridge.log")"
            sleep 0.1
        done
        [[ -s $STATE/link.json ]] || die "delay_bridge did not start within 10 s"
    else
        die "HT_LINK must be auto, bridge or netem, got '$LINK'"
    fi
    echo "$PROG: up: $NS_LAB ($LAB_IP) <-> $NS_VE ($VE_IP) through $NS_LINK:" \
        "$use, delay ${delay_ms} ms +-$(awk -v j="$JITTER" 'BEGIN { print j * 100 }') %," \
        "loss $(awk -v l="$LOSS" 'BEGIN { print l * 100 }') %"
}

# Stop a process we started, by pid: SIGINT, then SIGKILL after 5 s.
stop_pid() {
    local pid=$1 i
    kill -INT "$pid" 2>/dev/null || return 0
    for i in $(seq 50); do
        kill -0 "$pid" 2>/dev/null || return 0
        sleep 0.1
    done
    kill -KILL "$pid" 2>/dev/null || true
}

cmd_down() {
    if [[ -f $STATE/bridge.pid ]]; then
        stop_pid "$(cat "$STATE/bridge.pid")"
        rm -f "$STATE/bridge.pid"
    fi
    if ns_exists "$NS_LINK" && ip netns exec "$NS_LINK" tc qdisc show dev llab 2>/dev/null \
            | grep -q netem; then
        # netem's own counters (sent, dropped) into link.json.
        ip netns exec "$NS_LINK" tc -s -j qdisc show >"$STATE/netem_stats.json" 2>/dev/null || true
    fi
    local ns pid
    for ns in "$NS_LAB" "$NS_VE" "$NS_LINK"; do
        if ns_exists "$ns"; then
            # Processes still inside (only ours can be: the namespaces are this script's).
            for pid in $(ip netns pids "$ns" 2>/dev/null); do stop_pid "$pid"; done
            ip netns del "$ns"
        fi
    done
}

cmd_run() {
    local scenario=${1:?usage: $PROG run SCENARIO DELAY_MS [run options]}
    local delay_ms=${2:?usage: $PROG run SCENARIO DELAY_MS [run options]}
    shift 2
    local out=${OUT:-bags/two_hosts_$(basename "$scenario" .yaml)_${delay_ms}ms_$(date +%Y%m%d-%H%M%S)}
    trap cmd_down EXIT
    trap 'exit 130' INT TERM
    cmd_up "$delay_ms"
    local status=0
    ip netns exec "$NS_LAB" "${DDS_ENV[@]}" "$VENV/bin/haptic-topology" run "$scenario" \
        --out "$out" --node-prefix "ve_sim=ip netns exec $NS_VE" "$@" || status=$?
    cmd_down
    trap - EXIT
    if [[ -d $out ]]; then
        cp "$STATE/link.json" "$out/link.json" 2>/dev/null || true
        [[ -f $STATE/netem_stats.json ]] && cp "$STATE/netem_stats.json" "$out/"
        echo "$PROG: link counters: $out/link.json"
    fi
    return "$status"
}

# The device on the far side: device-server in ${P}ve, the graph in ${P}lab (see the header).
cmd_run_device() {
    local scenario=${1:?usage: $PROG run-device SCENARIO DELAY_MS [run options]}
    local delay_ms=${2:?usage: $PROG run-device SCENARIO DELAY_MS [run options]}
    shift 2
    local out=${OUT:-bags/two_hosts_device_$(basename "$scenario" .yaml)_${delay_ms}ms_$(date +%Y%m%d-%H%M%S)}
    local port=${HT_DEVICE_PORT:-47001}
    trap cmd_down EXIT
    trap 'exit 130' INT TERM
    cmd_up "$delay_ms"
    rm -f "$STATE/device_ready.json" "$STATE/device_server.json" "$STATE/device_server_cpu.json" \
        "$STATE/device_server_log.csv" "$STATE/forger.json"
    local key=${HT_DEVICE_KEY:-} auth=()
    if [[ $key == none ]]; then
        auth=(--trusted-network); key=''
    else
        if [[ -z $key ]]; then
            key=$STATE/device.key
            rm -f "$key"
            "$VENV/bin/haptic-topology" device-key "$key" >/dev/null
        fi
        auth=(--key-file "$key")
    fi
    "$PY" - "${HT_PARAMS:-$REPO/config/haptic_topology.yaml}" "$STATE/params.yaml" "$VE_IP" \
        "$port" "${HT_DEVICE_OPTIONS:-}" "$key" <<'PYEOF'
import sys
import yaml
src, dst, host, port, extra, key = sys.argv[1:]
with open(src, encoding='utf-8') as f:
    params = yaml.safe_load(f)
p = params.setdefault('device_driver', {}).setdefault('ros__parameters', {})
p['backend'] = 'network'
auth = f'key_file: {key}' if key else 'trusted_network: true'
p['backend_options'] = '{host: %s, port: %s, %s%s}' % (host, port, auth,
                                                       ', ' + extra if extra else '')
with open(dst, 'w', encoding='utf-8') as f:
    yaml.safe_dump(params, f, sort_keys=False)
PYEOF
    local rt=()
    [[ ${HT_DEVICE_PRIORITY:-0} -gt 0 ]] && rt=(chrt -f "$HT_DEVICE_PRIORITY")
    setsid ip netns exec "$NS_VE" "${rt[@]}" "$VENV/bin/haptic-topology" device-server \
        --scenario "$scenario" --host "$VE_IP" --port "$port" \
        --ready-file "$STATE/device_ready.json" --summary "$STATE/device_server.json" \
        --log "$STATE/device_server_log.csv" "${auth[@]}" >"$STATE/device_server.log" 2>&1 &
    local dpid=$! i
    for i in $(seq 300); do
        [[ -s $STATE/device_ready.json ]] && break
        kill -0 "$dpid" 2>/dev/null \
            || die "device-server exited: $(tail -n 3 "$STATE/device_server.log")"
        sleep 0.1
    done
    [[ -s $STATE/device_ready.json ]] || die "device-server did not serve within 30 s"
    echo "$PROG: device-server on $NS_VE $VE_IP:$port (pid $dpid), link" \
        "$("$PY" -c 'import json, sys; print(json.load(open(sys.argv[1]))["link"])' \
        "$STATE/device_ready.json")"
    local fpid=''
    if [[ ${HT_FORGER:-0} == 1 ]]; then
        setsid ip netns exec "$NS_LAB" "$PY" "$REPO/scripts/link_forger.py" --iface lab0 \
            --device "$VE_IP:$port" --out "$STATE/forger.json" >"$STATE/forger.log" 2>&1 &
        fpid=$!
        echo "$PROG: a forger on the link in $NS_LAB (pid $fpid)"
    fi
    local status=0
    ip netns exec "$NS_LAB" "$VENV/bin/haptic-topology" run "$scenario" --out "$out" \
        --params "$STATE/params.yaml" "$@" || status=$?
    [[ -n $fpid ]] && stop_pid "$fpid"
    # The server's CPU time (utime + stime, clock ticks) and age, before it stops.
    awk -v hz="$(getconf CLK_TCK)" -v up="$(cut -d' ' -f1 /proc/uptime)" \
        '{ printf "{\"cpu_s\": %.2f, \"wall_s\": %.2f}\n", ($14 + $15) / hz, up - $22 / hz }' \
        "/proc/$dpid/stat" >"$STATE/device_server_cpu.json" 2>/dev/null || true
    stop_pid "$dpid"
    cmd_down
    trap - EXIT
    if [[ -d $out ]]; then
        local f
        cp "$STATE/link.json" "$out/link.json" 2>/dev/null || true
        for f in device_server.json device_server.log device_server_cpu.json \
                device_server_log.csv forger.json; do
            cp "$STATE/$f" "$out/" 2>/dev/null || true
        done
        echo "$PROG: link counters: $out/link.json, device server: $out/device_server.json"
    fi
    return "$status"
}

cmd=${1:-}
[[ $# -gt 0 ]] && shift
case $cmd in
    check)
        reason=$(why_not)
        if [[ -n $reason ]]; then echo "$PROG: cannot run here: $reason"; exit 1; fi
        echo "$PROG: ok (root, network namespaces, veth)"
        ;;
    up) skip_unless_root; cmd_up "$@" ;;
    down) skip_unless_root; cmd_down ;;
    run) skip_unless_root; cmd_run "$@" ;;
    run-device) skip_unless_root; cmd_run_device "$@" ;;
    exec)
        skip_unless_root
        side=${1:?usage: $PROG exec lab|ve CMD ...}; shift
        case $side in lab) ns=$NS_LAB ;; ve) ns=$NS_VE ;; *) die "exec: lab or ve, got '$side'" ;; esac
        ip netns exec "$ns" "${DDS_ENV[@]}" "$@"
        ;;
    *)
        sed -n '2,/^set -euo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'
        [[ -z $cmd ]] && exit 0
        exit 2
        ;;
esac

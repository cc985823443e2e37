#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for trying `ctxrace sweep --emit slurm` as a cluster
# runs it (and for deploy/slurm_test.sh). Needs root (it runs slurmctld, slurmd and munged as
# root, without cgroups); installs Debian's slurm-wlm and munge when they are missing.
#
#   deploy/slurm-one-node.sh start [STATE_DIR]   # then: export SLURM_CONF=STATE_DIR/slurm.conf
#   deploy/slurm-one-node.sh stop [STATE_DIR]
#
# STATE_DIR (default /tmp/ctxrace-slurm) holds the config, state, spool, logs and pid files.
# Facts it relies on: ../shared/spec/slurm-one-node.md.
set -euo pipefail
action=${1:-}
state=${2:-/tmp/ctxrace-slurm}
conf=$state/slurm.conf

die() { echo "slurm-one-node: $*" >&2; exit 1; }

install() {
    command -v slurmctld >/dev/null && command -v munged >/dev/null && return
    [[ $(id -u) == 0 ]] || die "slurm-wlm and munge are missing; run as root to install them"
    echo "slurm-one-node: installing slurm-wlm and munge" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -qq slurm-wlm munge >/dev/null ||
        { apt-get update -qq && apt-get install -y -qq slurm-wlm munge >/dev/null; } ||
        die "apt-get could not install slurm-wlm and munge"
}

start_munge() {
    if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then return; fi
    if [[ ! -s /etc/munge/munge.key ]]; then
        mkdir -p /etc/munge
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
    fi
    chown munge:munge /etc/munge/munge.key 2>/dev/null || true
    chmod 0400 /etc/munge/munge.key
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge 2>/dev/null || true
    munged --force --pid-file="$state/munged.pid"
    for _ in $(seq 50); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && return
        sleep 0.1
    done
    die "munged did not start (see /var/log/munge/munged.log)"
}

write_conf() {
    local host cpus mem
    host=$(hostname -s)
    cpus=$(nproc)
    # below the machine's memory, as slurmd requires
    mem=$(awk '/MemTotal/ { printf "%d", $2 / 1024 * 0.9 }' /proc/meminfo)
    mkdir -p "$state/ctld" "$state/spool"
    cat >"$conf" <<CONF
ClusterName=ctxrace
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$state/ctld
SlurmdSpoolDir=$state/spool
SlurmctldPidFile=$state/slurmctld.pid
SlurmdPidFile=$state/slurmd.pid
SlurmctldLogFile=$state/slurmctld.log
SlurmdLogFile=$state/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MpiDefault=none
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
}

stop_pid() {
    local file=$1 pid
    [[ -s $file ]] || return 0
    pid=$(cat "$file")
    if kill "$pid" 2>/dev/null; then
        for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    fi
    rm -f "$file"
}

case $action in
start)
    install
    mkdir -p "$state"
    start_munge
    write_conf
    export SLURM_CONF=$conf
    stop_pid "$state/slurmd.pid"
    stop_pid "$state/slurmctld.pid"
    slurmctld -f "$conf"
    slurmd -f "$conf"
    for _ in $(seq 100); do
        if sinfo -h -o %T 2>/dev/null | grep -qx idle; then
            echo "slurm-one-node: up ($(nproc) CPUs); export SLURM_CONF=$conf" >&2
            exit 0
        fi
        sleep 0.2
    done
    die "the node is not idle after 20 s: see $state/slurmctld.log and $state/slurmd.log"
    ;;
stop)
    stop_pid "$state/slurmd.pid"
    stop_pid "$state/slurmctld.pid"
    stop_pid "$state/munged.pid"
    echo "slurm-one-node: stopped" >&2
    ;;
*)
    die "usage: $0 start|stop [STATE_DIR]"
    ;;
esac

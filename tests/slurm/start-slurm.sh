#!/usr/bin/env bash
# A single-node Slurm on this machine, for the tests of `packings enumerate --slurm`
# (tests/service/test_slurm.py): munged, slurmctld and slurmd on localhost, one partition, debug, of
# this machine's cores, jobs run as root.  Needs root and Debian's slurm-wlm and munge (.ci/run installs
# them).  Safe to run again: daemons that answer are left alone, and a slurm.conf that this script did
# not write is used as it is.  Ends once sinfo shows the node up (exit 0), or fails after a deadline.
set -euo pipefail
CONF=${SLURM_CONF:-/etc/slurm/slurm.conf}
MARK="# written by packings' tests/slurm/start-slurm.sh"
STATE=/var/spool/slurm-packings
LOGS=/var/log/slurm
host=$(hostname -s)

if [ ! -f "$CONF" ] || [ "$(head -1 "$CONF")" = "$MARK" ]; then
    node=$(slurmd -C | head -1)  # NodeName=<host> CPUs=... RealMemory=...: this machine as slurmd sees it
    mkdir -p "$(dirname "$CONF")" "$STATE/ctld" "$STATE/d" "$LOGS"
    cat >"$CONF.new" <<CONF
$MARK
ClusterName=packings
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
# no cgroups: processes are tracked by their parents, which a container allows
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
# a node that was down comes back by itself; a cancelled job's processes get SIGKILL 5 s after SIGTERM
ReturnToService=2
KillWait=5
MinJobAge=60
InactiveLimit=0
$node State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
    mv "$CONF.new" "$CONF"
fi

# munge: the key the package made (or a new one), and its daemon, run as its own user
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    if [ ! -s /etc/munge/munge.key ]; then
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
    fi
    chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge && chown munge:munge /run/munge
    runuser -u munge -- /usr/sbin/munged
    for _ in $(seq 50); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
        sleep 0.2
    done
fi

alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
alive /run/slurmctld.pid || slurmctld
alive /run/slurmd.pid || slurmd

# poll until the node is up (idle, or running jobs already), for at most a minute
for _ in $(seq 120); do
    state=$(sinfo -h -N -n "$host" -o %t 2>/dev/null | head -1 || true)
    case "$state" in
        idle | mix | alloc) exit 0 ;;
        down* | drain*) scontrol update nodename="$host" state=resume 2>/dev/null || true ;;
    esac
    sleep 0.5
done
echo "start-slurm: the node $host is not up after 60 s (state: ${state:-none}); see $LOGS" >&2
exit 1

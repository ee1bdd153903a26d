#!/usr/bin/env bash
# Run the tiny campaign through profiles/slurm on a real single-node SLURM, and check
# that its results equal a local run's.
#
#   bash scripts/slurm_ci.sh            (as root on a Debian/Ubuntu machine; CI calls it)
#
# 1. installs munge, slurmctld, slurmd and the client tools from the distribution's
#    packages (if missing) and writes a one-node /etc/slurm/slurm.conf for this host
#    (CPUs and memory from `slurmd -C`; no accounting, so job states come from squeue);
# 2. starts munged, slurmctld and slurmd, and stops, on every exit, the daemons it started;
# 3. checks that a GPU request is refused before any job on this cluster without GPUs;
# 4. runs the tiny campaign locally and through the profile at the same time, its shard
#    and profile jobs bundled into one group job each (the profile's group-components), cancels
#    the training job once while it runs on SLURM (the profile's retries resubmit it and
#    it resumes from its checkpoint), checks that SLURM ran as many jobs as
#    `subslope cluster-jobs` counts in the dry run (plus the resubmission), and compares
#    the two results folders with `subslope compare-runs`.
#
# Knobs: SLURM_CI_DIR (work folder, default a new temporary one), SLURM_CI_KEEP=1 keeps it.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PY="$REPO/.venv/bin/python"
SNAKEMAKE="$REPO/.venv/bin/snakemake"
WORK=${SLURM_CI_DIR:-$(mktemp -d /tmp/subslope-slurm-ci.XXXXXX)}
CONF=/etc/slurm/slurm.conf
MARK="# written by subslope scripts/slurm_ci.sh"
STATE="$WORK/slurm"
STARTED=()
t0=$(date +%s)

say() { echo "slurm_ci: $*"; }

stop_daemons() {
    for name in "${STARTED[@]}"; do
        pkill -x "$name" 2>/dev/null || true
    done
    # a daemon writes its state while it shuts down: wait for it before removing that
    for name in "${STARTED[@]}"; do
        for _ in $(seq 50); do
            pgrep -x "$name" >/dev/null || break
            sleep 0.2
        done
        pkill -9 -x "$name" 2>/dev/null || true
    done
    if [ "${SLURM_CI_KEEP:-0}" != 1 ]; then
        rm -rf "$WORK" || { sleep 1; rm -rf "$WORK"; }
    fi
    say "stopped ${STARTED[*]:-nothing}; took $(( $(date +%s) - t0 )) s in all"
}
trap stop_daemons EXIT

[ "$(id -u)" = 0 ] || { say "needs root (apt-get, daemons)"; exit 1; }

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    say "installing munge slurmctld slurmd slurm-client"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q munge slurmctld slurmd slurm-client \
        >"$WORK/apt.log" 2>&1 || {
        apt-get update -q >>"$WORK/apt.log" 2>&1
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q munge slurmctld slurmd \
            slurm-client >>"$WORK/apt.log" 2>&1
    }
fi

if [ -e "$CONF" ] && ! grep -qF "$MARK" "$CONF"; then
    say "$CONF exists and was not written by this script; not touching a real cluster"
    exit 1
fi
mkdir -p "$STATE/state" "$STATE/spool" "$STATE/log" /etc/slurm
node=$(hostname -s)
cpus=$(slurmd -C | sed -n 's/.*CPUs=\([0-9]*\).*/\1/p' | head -1)
mem=$(slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' | head -1)
cat >"$CONF" <<EOF
$MARK
ClusterName=subslope-ci
SlurmctldHost=$node
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/state
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/log/jobcomp.txt
JobAcctGatherType=jobacct_gather/none
MinJobAge=600
ReturnToService=2
SchedulerType=sched/backfill
MpiDefault=none
NodeName=$node CPUs=$cpus RealMemory=$(( mem * 9 / 10 )) State=UNKNOWN
PartitionName=ci Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF

if ! pgrep -x munged >/dev/null; then
    mkdir -p /run/munge && chown munge:munge /run/munge
    su -s /bin/sh munge -c munged && STARTED+=(munged)
fi
for daemon in slurmctld slurmd; do
    pgrep -x "$daemon" >/dev/null && { say "$daemon already runs; using it"; continue; }
    "$daemon" && STARTED+=("$daemon")
done
for _ in $(seq 30); do
    sinfo -h -o %t 2>/dev/null | grep -q idle && break
    sleep 1
done
sinfo -h -o "%P %D %t %c %m %G" | sed 's/^/slurm_ci: sinfo: /'
say "SLURM up after $(( $(date +%s) - t0 )) s"

# Two work folders holding the workflow, the configs and the profile, as a user has them.
for run in local slurm; do
    mkdir -p "$WORK/$run"
    cp "$REPO/Snakefile" "$WORK/$run/"
    cp -r "$REPO/workflow" "$REPO/config" "$REPO/profiles" "$WORK/$run/"
done
export SUBSLOPE_DATA_MIRROR=${SUBSLOPE_DATA_MIRROR:-$REPO/../shared/data}
export OMP_NUM_THREADS=1

# A GPU request on this cluster without GPUs: refused before any job is submitted.
printf 'base: tiny.yaml\ntraining: {gpus: 1}\n' >"$WORK/slurm/config/tiny_gpu.yaml"
if (cd "$WORK/slurm" && "$SNAKEMAKE" --profile profiles/slurm \
        --configfile config/tiny_gpu.yaml >"$WORK/gpu.log" 2>&1); then
    say "a GPU request on a cluster without GPUs was accepted"; exit 1
fi
grep -q "config key training.gpus = 1: the SLURM cluster offers no GPU" "$WORK/gpu.log" || {
    cat "$WORK/gpu.log"; say "no error naming training.gpus"; exit 1
}
[ -z "$(squeue -h)" ] || { say "jobs were submitted for a refused config"; exit 1; }
say "GPU request refused before any job"

predicted=$(cd "$WORK/slurm" && "$REPO/.venv/bin/subslope" cluster-jobs --total -- \
    --profile profiles/slurm --configfile config/tiny.yaml)
say "the dry run counts $predicted cluster jobs"

(cd "$WORK/local" && "$SNAKEMAKE" --cores 1 --configfile config/tiny.yaml \
    >"$WORK/local.log" 2>&1) &
local_pid=$!

# Cancel the training job once while it runs: the profile's retries must bring it back.
(
    for _ in $(seq 600); do
        job=$(squeue -h -t R -o "%i %k" | awk '/train_estimator/ {print $1; exit}')
        if [ -n "$job" ]; then
            sleep 2
            scancel "$job" && echo "cancelled SLURM job $job (train_estimator)" >"$WORK/cancelled"
            exit 0
        fi
        sleep 1
    done
) &
canceller=$!

t1=$(date +%s)
if ! (cd "$WORK/slurm" && timeout 1500 "$SNAKEMAKE" --profile profiles/slurm \
        --configfile config/tiny.yaml >"$WORK/slurm.log" 2>&1); then
    tail -40 "$WORK/slurm.log"; say "the campaign through profiles/slurm failed"; exit 1
fi
say "tiny campaign through profiles/slurm: $(( $(date +%s) - t1 )) s"
kill "$canceller" 2>/dev/null || true
wait "$local_pid" || { tail -40 "$WORK/local.log"; say "the local run failed"; exit 1; }
if [ -f "$WORK/cancelled" ]; then
    say "$(cat "$WORK/cancelled"); the run resubmitted it and finished"
else
    say "training finished before it could be cancelled"
fi
submitted=$(grep -c . "$STATE/log/jobcomp.txt")
expected=$(( predicted + $([ -f "$WORK/cancelled" ] && echo 1 || echo 0) ))
say "SLURM ran $submitted jobs; the dry run's count (and a resubmission) gives $expected"
[ "$submitted" = "$expected" ] || { say "job count differs from the dry run's"; exit 1; }

"$PY" -m subslope.cli compare-runs "$WORK/local/results" "$WORK/slurm/results" \
    >"$WORK/compare.log" 2>&1 || {
    cat "$WORK/compare.log"; say "SLURM results differ from the local run's"; exit 1
}
say "results equal the local run's ($(grep -c . "$WORK/compare.log") files compared)"

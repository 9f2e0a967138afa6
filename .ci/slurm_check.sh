#!/usr/bin/env bash
# Single-node Slurm check of `sos bench` sharding, for a root shell on Debian bookworm (2 cores
# are enough). Called by .ci/run after `cargo build --release -p sos`; runs from the repo root.
#
# 1. installs slurm-wlm and munge with apt-get (skipped when already installed);
# 2. writes a munge key and a single-node /etc/slurm/slurm.conf for this host, starts munged,
#    slurmctld and slurmd, and waits until `sinfo` shows the node idle;
# 3. runs the single-process reference `sos bench benchmarks/run_all.toml --profile tiny`;
# 4. submits the same profile as a 2-task array (1 CPU, RAYON_NUM_THREADS=1 per task, so both
#    run at once) plus the dependent merge job via benchmarks/slurm/submit.sh, waits for both;
# 5. requires every job to have completed with exit code 0, and
#    `sos bench diff <single> <slurm>/merged` to exit 0 (identical metric for metric).
# Every daemon it started is stopped on exit (by PID), on failure too; on failure the job logs
# and the daemon logs are printed. Results and logs stay in the work folder it prints.
#
# Environment:
#   SOS_BIN           the sos binary (default target/release/sos)
#   SOS_CHECK_DIR     work folder (default: a new mktemp -d under ${TMPDIR:-/tmp})
#   SOS_CHECK_TIMEOUT seconds to wait for the Slurm jobs (default 900)
#   SOS_CHECK_BENCH   benchmark file (default benchmarks/run_all.toml)
#   SOS_CHECK_PROFILE profile of the benchmark file to run (default tiny)
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$(pwd)

SOS_BIN=${SOS_BIN:-target/release/sos}
case $SOS_BIN in /*) ;; */*) SOS_BIN="$REPO/$SOS_BIN" ;; esac
PROFILE=${SOS_CHECK_PROFILE:-tiny}
BENCH=${SOS_CHECK_BENCH:-benchmarks/run_all.toml}
TIMEOUT=${SOS_CHECK_TIMEOUT:-900}
SHARDS=2

log() { echo "[slurm-check $(date +%T)] $*"; }
die() { echo "[slurm-check $(date +%T)] FAILED: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "must run as root (installs packages, writes /etc/slurm, starts daemons)"
[ -x "$SOS_BIN" ] || command -v "$SOS_BIN" >/dev/null || die "$SOS_BIN not found (cargo build --release -p sos)"
[ -f "$BENCH" ] || die "$BENCH not found"

t_start=$(date +%s)
WORK=${SOS_CHECK_DIR:-$(mktemp -d "${TMPDIR:-/tmp}/sos-slurm-check.XXXXXX")}
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
rm -rf "$WORK/single" "$WORK/slurm" "$WORK/state" "$WORK/daemons"
DLOG=$WORK/daemons
STATE=$WORK/state
mkdir -p "$DLOG" "$STATE/ctld" "$STATE/slurmd"
log "work folder: $WORK"

# --------------------------------------------------------------------------------------------
# Teardown: cancel our jobs, stop the daemons we started (by PID), print logs on failure.
MUNGED_PID=""
SLURMCTLD_PID=""
SLURMD_PID=""
ARRAY_ID=""
MERGE_ID=""
POLICY_RC_CREATED=0

print_logs() {
  echo "================ job logs ($WORK/slurm/logs)"
  local f
  for f in "$WORK"/slurm/logs/*; do
    [ -f "$f" ] || continue
    echo "---------------- $f"
    cat "$f"
  done
  if [ -n "$ARRAY_ID$MERGE_ID" ] && [ -n "$SLURMCTLD_PID" ]; then
    echo "================ scontrol show job"
    for j in $ARRAY_ID $MERGE_ID; do timeout 10 scontrol show job "$j" || true; done
    echo "================ sinfo"
    timeout 10 sinfo -N -l || true
  fi
  for f in "$DLOG"/*; do
    [ -f "$f" ] || continue
    echo "================ last 40 lines of $f"
    tail -n 40 "$f"
  done
}

stop_pid() { # name pid
  local name=$1 pid=$2 i
  [ -n "$pid" ] || return 0
  kill -0 "$pid" 2>/dev/null || { log "$name ($pid) already gone"; return 0; }
  kill -TERM "$pid" 2>/dev/null || true
  for (( i = 0; i < 100; i++ )); do
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.2
  done
  if kill -0 "$pid" 2>/dev/null; then
    log "$name ($pid) did not stop on TERM, killing it"
    kill -KILL "$pid" 2>/dev/null || true
  fi
  wait "$pid" 2>/dev/null || true
  log "stopped $name ($pid)"
}

cleanup() {
  local rc=$?
  set +e
  trap - EXIT INT TERM
  if [ "$rc" != 0 ]; then
    print_logs >&2
  fi
  if [ -n "$SLURMCTLD_PID" ] && [ -n "$ARRAY_ID$MERGE_ID" ]; then
    # Jobs still queued or running (timeout, interrupt): cancel them before slurmd goes away.
    if [ -n "$(timeout 10 squeue -h -j "${ARRAY_ID}${MERGE_ID:+,$MERGE_ID}" -o %i 2>/dev/null)" ]; then
      log "cancelling jobs $ARRAY_ID $MERGE_ID"
      timeout 10 scancel $ARRAY_ID $MERGE_ID
      for (( i = 0; i < 30; i++ )); do
        [ -z "$(timeout 10 squeue -h -j "${ARRAY_ID}${MERGE_ID:+,$MERGE_ID}" -o %i 2>/dev/null)" ] && break
        sleep 1
      done
    fi
  fi
  if [ -n "$SLURMD_PID" ]; then
    # A job counts as finished slightly before its slurmstepd exits: give those a few seconds.
    # Any slurmstepd is ours (none ran when this script started).
    for (( i = 0; i < 50; i++ )); do
      pgrep -x slurmstepd >/dev/null || break
      sleep 0.2
    done
    for pid in $(pgrep -x slurmstepd); do stop_pid slurmstepd "$pid"; done
  fi
  stop_pid slurmd "$SLURMD_PID"
  stop_pid slurmctld "$SLURMCTLD_PID"
  stop_pid munged "$MUNGED_PID"
  [ "$POLICY_RC_CREATED" = 1 ] && rm -f /usr/sbin/policy-rc.d
  if [ "$rc" = 0 ]; then
    log "PASSED in $(( $(date +%s) - t_start )) s; results in $WORK"
  else
    log "FAILED (exit code $rc) after $(( $(date +%s) - t_start )) s; results and logs in $WORK" >&2
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

# --------------------------------------------------------------------------------------------
# 1. Packages
installed() { [ "$(dpkg-query -W -f='${Status}' "$1" 2>/dev/null)" = "install ok installed" ]; }
if installed slurm-wlm && installed munge; then
  log "slurm-wlm and munge already installed"
else
  log "installing slurm-wlm and munge"
  # No service may start during the install (the munge/slurm init scripts would start daemons
  # that this script does not own): a policy-rc.d that denies, unless one is already there.
  if [ ! -e /usr/sbin/policy-rc.d ]; then
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d
    chmod +x /usr/sbin/policy-rc.d
    POLICY_RC_CREATED=1
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q
  apt-get install -y -q --no-install-recommends slurm-wlm munge
  if [ "$POLICY_RC_CREATED" = 1 ]; then rm -f /usr/sbin/policy-rc.d; POLICY_RC_CREATED=0; fi
fi
for c in munged munge unmunge slurmctld slurmd sbatch squeue scontrol sinfo scancel; do
  command -v "$c" >/dev/null || die "$c not found after installing slurm-wlm and munge"
done
log "$(slurmctld -V), munge $(munged -V 2>&1 | head -n1)"

for d in slurmctld slurmd slurmstepd; do
  if pgrep -x "$d" >/dev/null; then
    die "$d is already running on this machine; this check needs a machine without Slurm daemons"
  fi
done

# --------------------------------------------------------------------------------------------
# 2. munge key, slurm.conf, daemons
HOST=$(hostname -s)
CPUS=$(nproc)
MEM_MB=$(awk '/^MemTotal:/ { printf "%d", $2 / 1024 * 0.9 }' /proc/meminfo)

if pgrep -x munged >/dev/null; then
  munge -n | unmunge >/dev/null || die "a munged is running but does not work"
  log "reusing the munged already running"
else
  log "writing /etc/munge/munge.key, starting munged"
  install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
  install -d -o munge -g munge -m 0755 /run/munge
  dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
  chown munge:munge /etc/munge/munge.key
  chmod 0400 /etc/munge/munge.key
  # Foreground (-F), so $! is munged itself; as the munge user (setpriv execs, same PID).
  setpriv --reuid=munge --regid=munge --init-groups munged -F --force >"$DLOG/munged.log" 2>&1 &
  MUNGED_PID=$!
  for (( i = 0; i < 50; i++ )); do
    munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
    kill -0 "$MUNGED_PID" 2>/dev/null || die "munged exited at start"
    sleep 0.2
  done
  munge -n | unmunge >/dev/null || die "munged does not answer"
  log "munged running (pid $MUNGED_PID)"
fi

log "writing /etc/slurm/slurm.conf: node $HOST, $CPUS CPUs, $MEM_MB MB"
mkdir -p /etc/slurm
if [ -f /etc/slurm/slurm.conf ] && ! grep -q '^# written by nerf-sos .ci/slurm_check.sh' /etc/slurm/slurm.conf; then
  cp /etc/slurm/slurm.conf "/etc/slurm/slurm.conf.bak.$(date +%s)"
fi
cat > /etc/slurm/slurm.conf <<EOF
# written by nerf-sos .ci/slurm_check.sh: a single-node cluster for the CI check
ClusterName=sos-ci
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
# No cgroups: plain process tracking, no task binding.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
# Keep finished jobs in the controller for an hour, so scontrol still reports their state.
MinJobAge=3600
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/slurmd
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$DLOG/slurmctld.log
SlurmdLogFile=$DLOG/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
NodeName=$HOST CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=ci Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF

log "starting slurmctld and slurmd"
slurmctld -D -c >"$DLOG/slurmctld.out" 2>&1 &
SLURMCTLD_PID=$!
for (( i = 0; i < 60; i++ )); do
  timeout 5 scontrol ping 2>/dev/null | grep -q 'is UP' && break
  kill -0 "$SLURMCTLD_PID" 2>/dev/null || die "slurmctld exited at start"
  sleep 0.5
done
timeout 5 scontrol ping | grep -q 'is UP' || die "slurmctld does not answer"
slurmd -D >"$DLOG/slurmd.out" 2>&1 &
SLURMD_PID=$!
state=""
for (( i = 0; i < 120; i++ )); do
  state=$(timeout 5 sinfo -h -n "$HOST" -o %T 2>/dev/null || true)
  [ "$state" = idle ] && break
  kill -0 "$SLURMD_PID" 2>/dev/null || die "slurmd exited at start"
  sleep 0.5
done
[ "$state" = idle ] || die "node $HOST is '$state', not idle, after 60 s"
log "node $HOST idle (slurmctld pid $SLURMCTLD_PID, slurmd pid $SLURMD_PID)"

# --------------------------------------------------------------------------------------------
# 3. Single-process reference
log "reference: $SOS_BIN bench $BENCH --profile $PROFILE --out $WORK/single"
t0=$(date +%s)
"$SOS_BIN" bench "$BENCH" --profile "$PROFILE" --out "$WORK/single"
t_single=$(( $(date +%s) - t0 ))
log "reference finished in $t_single s"

# --------------------------------------------------------------------------------------------
# 4. Slurm: 2-task array + dependent merge
log "submitting the $SHARDS-task array and the merge job"
t0=$(date +%s)
ids=$(SOS_BIN="$SOS_BIN" SOS_BENCH="$BENCH" SOS_PROFILE="$PROFILE" SOS_OUT="$WORK/slurm" \
  SOS_CPUS_PER_TASK=1 SOS_ARRAY_TIME=00:15:00 benchmarks/slurm/submit.sh "$SHARDS")
echo "$ids"
ARRAY_ID=$(sed -n 's/^ARRAY_JOB_ID=//p' <<<"$ids")
MERGE_ID=$(sed -n 's/^MERGE_JOB_ID=//p' <<<"$ids")
[[ $ARRAY_ID =~ ^[0-9]+$ && $MERGE_ID =~ ^[0-9]+$ ]] || die "could not read the job ids from submit.sh"

# States of every record of a job (one per array task once they are split off).
job_states() { { timeout 10 scontrol -o show job "$1" | grep -o 'JobState=[A-Z_]*' | cut -d= -f2; } || true; }
terminal() {
  case $1 in
    COMPLETED|FAILED|CANCELLED|TIMEOUT|NODE_FAIL|OUT_OF_MEMORY|PREEMPTED|BOOT_FAIL|DEADLINE) return 0 ;;
    *) return 1 ;;
  esac
}
deadline=$(( $(date +%s) + TIMEOUT ))
max_running=0
last=""
while :; do
  states=$( { job_states "$ARRAY_ID"; job_states "$MERGE_ID"; } 2>/dev/null | tr '\n' ' ' || true)
  running=$( { timeout 10 squeue -h -j "$ARRAY_ID" -t RUNNING -o %i 2>/dev/null || true; } | wc -l)
  (( running > max_running )) && max_running=$running
  [ "$states" != "$last" ] && log "job states: array $ARRAY_ID + merge $MERGE_ID: $states"
  last=$states
  done_all=1
  for s in $states; do terminal "$s" || done_all=0; done
  [ -n "$states" ] && [ "$done_all" = 1 ] && break
  [ "$(date +%s)" -lt "$deadline" ] || die "jobs not finished after $TIMEOUT s"
  sleep 2
done
t_slurm=$(( $(date +%s) - t0 ))

# --------------------------------------------------------------------------------------------
# 5. Checks
bad=0
while read -r line; do
  [ -n "$line" ] || continue
  id=$(grep -o 'JobId=[0-9]*' <<<"$line" | head -n1 | cut -d= -f2)
  task=$(grep -o 'ArrayTaskId=[0-9]*' <<<"$line" | cut -d= -f2 || true)
  st=$(grep -o 'JobState=[A-Z_]*' <<<"$line" | cut -d= -f2)
  ec=$(grep -o ' ExitCode=[0-9:]*' <<<"$line" | cut -d= -f2)
  if [ -n "$task" ]; then name="array task ${ARRAY_ID}_$task (job $id)"; else name="merge job $id"; fi
  log "$name: $st, exit code $ec"
  [ "$st" = COMPLETED ] && [ "$ec" = 0:0 ] || bad=1
done < <(timeout 10 scontrol -o show job "$ARRAY_ID"; timeout 10 scontrol -o show job "$MERGE_ID")
[ "$bad" = 0 ] || die "a Slurm job did not complete with exit code 0"
[ "$(timeout 10 scontrol -o show job "$ARRAY_ID" | wc -l)" = "$SHARDS" ] || die "expected $SHARDS array tasks"
[ -f "$WORK/slurm/merged/report.md" ] || die "$WORK/slurm/merged/report.md missing"
if [ "$max_running" -lt "$SHARDS" ]; then
  log "note: the $SHARDS array tasks were not seen running at the same time (polled every 2 s)"
fi

log "sos bench diff $WORK/single $WORK/slurm/merged"
rc=0
"$SOS_BIN" bench diff "$WORK/single" "$WORK/slurm/merged" || rc=$?
[ "$rc" = 0 ] || die "sos bench diff exited with $rc: the Slurm results differ from the single-process ones"

log "reference $t_single s; Slurm array + merge $t_slurm s (submit to merge end; $max_running task(s) seen running at once)"

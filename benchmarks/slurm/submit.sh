#!/usr/bin/env bash
# Submits the `sos bench` matrix as a Slurm job array of N shards (run_all.sbatch), then the
# merge job (merge.sbatch) with --dependency=afterok on the array, and prints both job ids:
#   ARRAY_JOB_ID=<id>
#   MERGE_JOB_ID=<id>
#
# Usage, from the repository root (the jobs run there, so relative paths work; the folder must
# be on a file system that every compute node sees):
#   benchmarks/slurm/submit.sh N [sbatch options for both jobs...]
# e.g.
#   SOS_PROFILE=full SOS_OUT=/shared/sos/bench-2026-12 \
#     benchmarks/slurm/submit.sh 8 --partition=cpu --account=myproj
#
# Environment:
#   SOS_BIN, SOS_BENCH, SOS_PROFILE, SOS_OUT   as in run_all.sbatch (passed on to the jobs)
#   SOS_CPUS_PER_TASK   cores per array task (default: run_all.sbatch's --cpus-per-task, 2);
#                       RAYON_NUM_THREADS follows it
#   SOS_ARRAY_TIME      time limit per array task (default: run_all.sbatch's --time)
#   SOS_ARRAY_LIMIT     at most this many array tasks at once (--array=0-<N-1>%LIMIT)
# Logs go to $SOS_OUT/logs/. Results: $SOS_OUT/shard-<i>/ per task, $SOS_OUT/merged/ at the
# end. When a shard fails the merge job is cancelled (--kill-on-invalid-dep=yes); resubmit, and
# the finished runs are skipped.
set -euo pipefail

if [ $# -lt 1 ] || ! [[ $1 =~ ^[1-9][0-9]*$ ]]; then
  echo "usage: $0 N [sbatch options...]   (N = number of array tasks / shards, >= 1)" >&2
  exit 2
fi
N=$1
shift

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)

SOS_BIN=${SOS_BIN:-target/release/sos}
SOS_BENCH=${SOS_BENCH:-benchmarks/run_all.toml}
SOS_PROFILE=${SOS_PROFILE:-quick}
SOS_OUT=${SOS_OUT:-runs/bench-slurm}
mkdir -p "$SOS_OUT/logs"
# Absolute paths: the jobs may start in another working directory (--chdir in the options).
SOS_OUT=$(cd "$SOS_OUT" && pwd)
case $SOS_BIN in /*) ;; */*) SOS_BIN="$(pwd)/$SOS_BIN" ;; esac
case $SOS_BENCH in /*) ;; *) SOS_BENCH="$(pwd)/$SOS_BENCH" ;; esac
export SOS_BIN SOS_BENCH SOS_PROFILE SOS_OUT
export SOS_SHARDS=$N

array_opts=(--array="0-$((N - 1))${SOS_ARRAY_LIMIT:+%$SOS_ARRAY_LIMIT}")
[ -n "${SOS_CPUS_PER_TASK:-}" ] && array_opts+=(--cpus-per-task="$SOS_CPUS_PER_TASK")
[ -n "${SOS_ARRAY_TIME:-}" ] && array_opts+=(--time="$SOS_ARRAY_TIME")

# --export=ALL: some sites default to SBATCH_EXPORT=NONE, which would drop the SOS_* variables.
array_id=$(sbatch --parsable --export=ALL "${array_opts[@]}" \
  --output="$SOS_OUT/logs/%x-%A_%a.out" "$@" "$here/run_all.sbatch")
array_id=${array_id%%;*}   # --parsable prints "id" or "id;cluster"

merge_id=$(sbatch --parsable --export=ALL --dependency="afterok:$array_id" --kill-on-invalid-dep=yes \
  --output="$SOS_OUT/logs/%x-%j.out" "$@" "$here/merge.sbatch")
merge_id=${merge_id%%;*}

echo "ARRAY_JOB_ID=$array_id"
echo "MERGE_JOB_ID=$merge_id"

#!/usr/bin/env bash
# Builds another commit's `sos` for a benchmark method that runs another build (`program`,
# `config`), e.g. the commit an optimisation started from, so one report compares the two:
#   benchmarks/build_commit.sh b3a6cd8
# writes that commit's source to target/builds/<commit>/src and its binary to
# target/builds/<commit>/sos (builds share target/builds/cargo, so later ones build faster).
set -euo pipefail
rev=${1:?usage: benchmarks/build_commit.sh <commit>}
root=$(git -C "$(dirname "$0")" rev-parse --show-toplevel)
git -C "$root" rev-parse --verify --quiet "$rev^{commit}" >/dev/null \
  || { echo "error: \`$rev\` is not a commit of $root" >&2; exit 2; }
dest="$root/target/builds/$rev"
rm -rf "$dest/src"
mkdir -p "$dest/src"
git -C "$root" archive "$rev" | tar -x -C "$dest/src"
CARGO_TARGET_DIR="$root/target/builds/cargo" cargo build --release -p sos --manifest-path "$dest/src/Cargo.toml"
cp "$root/target/builds/cargo/release/sos" "$dest/sos.partial"
mv "$dest/sos.partial" "$dest/sos"
echo "built $rev: $dest/sos (configs in $dest/src/configs)"

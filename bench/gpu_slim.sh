#!/usr/bin/env bash
# What travels to a lent GPU machine is the work tree, at most 64 MiB with the carried .whl/ and gpu_state/. The
# published policies under docs/results/ (about 0.4 MB per CNN seed and snapshot, 25 MB for the 10-seed Coordination
# Ring study alone) are not read there, so before a call that would not fit they leave the work tree, and come back
# from git after it:
#   bash bench/gpu_slim.sh            # before the device call: removes them from the work tree (not from git)
#   git checkout -- docs/results      # after it (bench/gpu_report.py first if files came back)
# A policy file with uncommitted changes, or one git does not track, stops it before anything is removed.
set -euo pipefail
cd "$(dirname "$0")/.."
untracked=$(git ls-files --others --exclude-standard -- 'docs/results/*.ocv2policy')
changed=$(git status --porcelain -- 'docs/results/*.ocv2policy' | grep -v '^ D' || true)
if [[ -n "$untracked$changed" ]]; then
    echo "gpu_slim: policies not committed as they are; commit them first (nothing was removed):" >&2
    printf '%s\n%s\n' "$untracked" "$changed" | sed '/^$/d' >&2
    exit 1
fi
mapfile -t files < <(git ls-files -- 'docs/results/*.ocv2policy')
bytes=0
for f in "${files[@]}"; do
    if [[ -f "$f" ]]; then bytes=$((bytes + $(stat -c %s "$f"))); rm "$f"; fi
done
echo "gpu_slim: ${#files[@]} published policies ($((bytes / 1048576)) MiB) left the work tree; after the call:"
echo "  git checkout -- docs/results"

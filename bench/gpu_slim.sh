#!/usr/bin/env bash
# What travels to a lent GPU machine is the work tree, at most 64 MiB with the carried .whl/ and gpu_state/. Two
# kinds of committed file are never read there: the published policies under docs/results/ (about 0.4 MB per CNN
# seed and snapshot, 25 MB for the 10-seed Coordination Ring study alone) and the CPU studies packed in study_state/
# (14-15 MB each). A 10-seed RNN gpu_state/ is about 40 MB, so before a call that would not fit they leave the work
# tree, and come back from git after it:
#   bash bench/gpu_slim.sh                           # before the device call: removes them from the work tree (not from git)
#   git checkout -- docs/results study_state         # after it (bench/gpu_report.py first if files came back)
# A file of either kind with uncommitted changes, or one git does not track, stops it before anything is removed.
set -euo pipefail
cd "$(dirname "$0")/.."
kinds=('docs/results/*.ocv2policy' 'study_state/*/*')
untracked=$(git ls-files --others --exclude-standard -- "${kinds[@]}")
changed=$(git status --porcelain -- "${kinds[@]}" | grep -v '^ D' || true)
if [[ -n "$untracked$changed" ]]; then
    echo "gpu_slim: published policies or study packs not committed as they are; commit them first (nothing was removed):" >&2
    printf '%s\n%s\n' "$untracked" "$changed" | sed '/^$/d' >&2
    exit 1
fi
report() {  # $1: what, then the files; removes those still in the work tree and says how many MiB left
    local what=$1 bytes=0 count=0
    shift
    for f in "$@"; do
        if [[ -f "$f" ]]; then bytes=$((bytes + $(stat -c %s "$f"))); count=$((count + 1)); rm "$f"; fi
    done
    echo "gpu_slim: ${count} ${what} ($((bytes / 1048576)) MiB) left the work tree"
}
mapfile -t policies < <(git ls-files -- "${kinds[0]}")
mapfile -t packs < <(git ls-files -- "${kinds[1]}")
report "published policies" "${policies[@]}"
report "study_state/ pack files" "${packs[@]}"
echo "after the call: git checkout -- docs/results study_state"

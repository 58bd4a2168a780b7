#!/usr/bin/env bash
# What travels to a lent GPU machine is the work tree, at most 64 MiB with the carried .whl/ and gpu_state/. Two
# kinds of committed file are never read there: the published policies under docs/results/ (about 0.4 MB per CNN
# seed and snapshot, 25 MB for the 10-seed Coordination Ring study alone) and the CPU studies packed in study_state/
# (14-15 MB each). A 10-seed RNN gpu_state/ is about 40 MB, so before a call that would not fit they leave the work
# tree and git's index (a deletion staged, not committed: whether the device tool sizes what travels from the work
# tree or from the index, they are out of both), and come back from git after it:
#   bash bench/gpu_slim.sh             # before the device call
#   bash bench/gpu_slim.sh --restore   # after it, before bench/gpu_report.py (which reads earlier policies)
# A file of either kind with uncommitted changes, or one git does not track, stops it before anything is removed;
# so does anything else staged (the restore unstages these paths, and a later commit must not take the deletions).
set -euo pipefail
cd "$(dirname "$0")/.."
paths=(docs/results study_state)
if [[ "${1:-}" == "--restore" ]]; then
    git reset -q -- "${paths[@]}"
    git checkout -- "${paths[@]}"
    echo "gpu_slim: docs/results and study_state restored from git"
    exit 0
fi
if ! git diff --cached --quiet; then
    if git diff --cached --quiet -- "${paths[@]}"; then
        echo "gpu_slim: something is staged already; commit or unstage it first (nothing was removed):" >&2
    else
        echo "gpu_slim: slimmed already (deletions staged); bash bench/gpu_slim.sh --restore brings them back:" >&2
    fi
    git diff --cached --name-status | head -5 >&2
    exit 1
fi
kinds=('docs/results/*.ocv2policy' 'study_state/*/*')
untracked=$(git ls-files --others --exclude-standard -- "${kinds[@]}")
changed=$(git status --porcelain -- "${kinds[@]}" | grep -v '^ D' || true)
if [[ -n "$untracked$changed" ]]; then
    echo "gpu_slim: published policies or study packs not committed as they are; commit them first (nothing was removed):" >&2
    printf '%s\n%s\n' "$untracked" "$changed" | sed '/^$/d' >&2
    exit 1
fi
report() {  # $1: what, then the files; removes them from the work tree and the index, says how many MiB left
    local what=$1 bytes=0 count=0
    shift
    for f in "$@"; do
        if [[ -f "$f" ]]; then bytes=$((bytes + $(stat -c %s "$f"))); count=$((count + 1)); fi
    done
    if (($# > 0)); then printf '%s\0' "$@" | xargs -0 git rm -q --ignore-unmatch --; fi  # index and work tree
    echo "gpu_slim: ${count} ${what} ($((bytes / 1048576)) MiB) left the work tree and the index"
}
mapfile -t policies < <(git ls-files -- "${kinds[0]}")
mapfile -t packs < <(git ls-files -- "${kinds[1]}")
report "published policies" "${policies[@]}"
report "study_state/ pack files" "${packs[@]}"
echo "after the call: bash bench/gpu_slim.sh --restore"

#!/usr/bin/env bash
# Training throughput of another commit ("before") and of this tree, same recipe, same machine, same run.
#
# Usage: bash benchmarks/training_before_after.sh [BEFORE_COMMIT] [OUT_DIR]
#   BEFORE_COMMIT  the tree to compare with (default 593aaa7, before the training-speed work)
#   OUT_DIR        where the training runs go (default a temporary directory)
#
# The recipe is the one shipped at 593aaa7: `icpbench train --preset quick-lidar`
# (no prior, bounded output, batch 2, 25 unrolled ICP iterations), shortened to SCANS training
# scans (default 12) and one epoch, one torch thread per process. It runs four times, one after
# the other: the before tree in one process and in two DDP processes (torchrun, gloo), then this
# tree the same two ways. The before tree is checked out into a detached worktree and installed
# (editable, no dependencies) into a virtual environment that sees the system's packages, so that
# its own package and its own plugin entry points run (with only PYTHONPATH, the entry points of
# the installed icpbench would import this tree's targets into the old package). Printed: scans per
# second of the epoch loop (from `train_wall_s` of each model card: data loading and evaluation
# excluded) and every row's throughput relative to the before tree's single process. Wall time, because two
# processes are faster only in wall time: run it on an otherwise idle machine.
set -euo pipefail
cd "$(dirname "$0")/.."
BEFORE=${1:-593aaa7}
OUT=${2:-$(mktemp -d)}
SCANS=${SCANS:-12}
OLD="$OUT/before-tree"
rm -rf "$OLD"
git worktree add --detach "$OLD" "$BEFORE" -q
trap 'git worktree remove --force "$OLD"' EXIT
python -m venv --system-site-packages "$OUT/before-venv"
"$OUT/before-venv/bin/python" -m pip install -q --no-deps -e "$OLD" > /dev/null 2>&1

ARGS=(train --preset quick-lidar --train-samples "$SCANS" --epochs 1 --eval-samples 1 --threads 1
      --quiet)
run() {  # run NAME TREE PYTHON NPROC
  local name=$1 tree=$2 py=$3 nproc=$4
  local launcher=(-m icpbench.cli)
  [ "$nproc" -gt 1 ] && launcher=(-m torch.distributed.run --standalone --nproc_per_node "$nproc"
                                  -m icpbench.cli)
  echo "== $name (tree $tree, $nproc process(es))" >&2
  (cd "$tree" && OMP_NUM_THREADS=1 PYTHONPATH="$tree" "$py" "${launcher[@]}" "${ARGS[@]}" \
      --out "$OUT/$name" > "$OUT/$name.log" 2>&1)
}
run before-1proc "$OLD" "$OUT/before-venv/bin/python" 1
run before-2proc "$OLD" "$OUT/before-venv/bin/python" 2
run after-1proc "$PWD" python 1
run after-2proc "$PWD" python 2

python - "$OUT" "$SCANS" <<'EOF'
import json, sys
from pathlib import Path

out, scans = Path(sys.argv[1]), int(sys.argv[2])
rows = {}
for name in ("before-1proc", "before-2proc", "after-1proc", "after-2proc"):
    card = json.loads((out / name / "generator.json").read_text())["card"]
    rows[name] = scans / card["train_wall_s"]
base = rows["before-1proc"]
print("| run | scans/s | x before, 1 process |")
print("|---|---|---|")
for name, rate in rows.items():
    print(f"| {name} | {rate:.3f} | {rate / base:.2f}x |")
EOF

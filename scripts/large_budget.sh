#!/usr/bin/env bash
# The large-budget check of the targets below 2x `uniform` on the 48-scan board (λ = 1 m, the
# first 12 scans): the ensemble through the target itself (`--surrogate self`: the target or its
# replica at its converged pose) with 20 PGD steps and a 2,000-query search per scan, then the
# worst case against the search budget (scripts/budget_curve.py) into results/large-budget/.
#
# Every run resumes where it stopped (rows are stored per scan), so the script can be stopped and
# started again, on another machine too. Cost on a 2-core machine with 2 workers: about 30 minutes
# per scan and worker for p2point and Open3D point-to-point, about an hour for KISS-ICP.
#
#   RUNS="open3d-p2point p2point" bash scripts/large_budget.sh   # some runs only (default: all)
#   CURVE_ONLY=1 bash scripts/large_budget.sh                    # only redraw the curves
#
# Set OMP_NUM_THREADS=1 and ICPBENCH_WORKERS (default: one per core) as for any processes run.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/large-budget
COMMON=(--attacks none,ensemble --surrogate self --budgets 1 --samples 12 --batch-size 1
        --executor processes --reference ensemble)
PGD=(--attack-param ensemble.queries=2000 --attack-param ensemble.pgd_steps=20)

run() {  # run NAME ARGS...: one resumable run into $OUT/NAME
  local name=$1; shift
  echo "== $name"
  icpbench run "${COMMON[@]}" "$@" --out "$OUT/$name"
}

ALL="p2point open3d-p2point kiss-icp small-gicp-plane-icp p2point-200q"
if [[ -z "${CURVE_ONLY:-}" ]]; then
  for r in ${RUNS:-$ALL}; do
    case $r in
      p2point) run p2point --targets p2point "${PGD[@]}" ;;
      open3d-p2point) run open3d-p2point --targets open3d --target-param open3d.mode=point \
        --target-param open3d.cauchy_c=null "${PGD[@]}" ;;
      kiss-icp) run kiss-icp --targets kiss-icp "${PGD[@]}" ;;
      # small_gicp's plane ICP has no replica, so its ensemble has no PGD member
      small-gicp-plane-icp) run small-gicp-plane-icp --targets small-gicp \
        --target-param small-gicp.registration_type=PLANE_ICP --attack-param ensemble.queries=2000 ;;
      p2point-200q) run p2point-200q --targets p2point --attack-param ensemble.queries=200 \
        --attack-param ensemble.pgd_steps=20 ;;
      *) echo "unknown run '$r' (one of: $ALL)" >&2; exit 2 ;;
    esac
  done
fi
folders=()
for r in $ALL; do [[ -f "$OUT/$r/results.csv" ]] && folders+=("$OUT/$r"); done
(( ${#folders[@]} )) || { echo "no finished rows under $OUT yet" >&2; exit 1; }
python scripts/budget_curve.py "${folders[@]}"

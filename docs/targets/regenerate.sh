#!/usr/bin/env bash
# Re-runs the fits behind docs/accuracy.md ("Fitted pipelines against the strongest GTAO", "Real meshes") and
# writes their outputs into docs/targets/: each fit's params.json, report.md and comparison.png, then the tables.
# Only the small tables (report.md, meshes/table.md, bench_quick_R0.5.md) are committed; params.json and
# comparison.png are regenerated here.
#
#   docs/targets/regenerate.sh [views2x3|first|meshes|bench|all]   (default: all)
#
# Long: each fit takes 5-35 minutes on one core; the first fits also ray-trace their views into $CACHE.
# Environment: PYTHON (default python), CACHE (reference cache, default refs), MODELS (assimp-testmodels,
# default /usr/share/assimp/models).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-python}
CACHE=${CACHE:-refs}
MODELS=${MODELS:-/usr/share/assimp/models}
T=docs/targets
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fit() { "$PY" -m torch_ao.cli fit "$@"; }

views2x3() {  # two training views and three held-out views per scene (the tables' first set: seeds 1000-1002)
  local P="--size 320x180 --max-distance 0.5 --preset high --spp 1024 --train-views 2 --holdout-views 3 --cache $CACHE --no-progress"
  fit --method gtao --fetch edge_aware $P --out $T/views2x3/gtao_edge
  fit --method gtao $P --out $T/views2x3/gtao
  fit --variant exact --thickness backface --fetch edge_aware $P --out $T/views2x3/exact_backface_edge
  fit --thickness backface --fetch edge_aware $P --out $T/views2x3/backface_edge
  fit --variant exact --thickness backface --fetch edge_aware --params thickness_scale,thickness $P \
      --out $T/views2x3/exact_backface_edge_R
  fit --fetch edge_aware $P --out $T/views2x3/edge
  local V=$T/views2x3
  "$PY" $T/table.py $V/{backface_edge,exact_backface_edge,exact_backface_edge_R,edge}/params.json \
      --gtao $V/{gtao,gtao_edge}/params.json
  "$PY" $T/more_holdout.py --seeds 1003,1004,1005 --cache "$CACHE" \
      --bitmask $V/{backface_edge,exact_backface_edge,exact_backface_edge_R}/params.json --gtao $V/{gtao,gtao_edge}/params.json
}

first() {  # one training view and one held-out view per scene
  local C="--size 320x180 --max-distance 0.5 --preset high --spp 1024 --train-views 1 --cache $CACHE --no-progress"
  fit --method bitmask $C --out $T/bitmask
  fit --method bitmask --variant exact $C --out $T/exact
  fit --method bitmask --thickness linear $C --out $T/linear
  fit --method bitmask --thickness backface $C --out $T/backface
  fit --method bitmask --thickness backface --fetch edge_aware $C --out $T/backface_edge
  fit --method bitmask --variant exact --thickness backface --fetch edge_aware $C --out $T/exact_backface_edge
  fit --method bitmask --fetch edge_aware $C --out $T/edge
  fit --method gtao $C --out $T/gtao
  fit --method gtao --fetch edge_aware $C --out $T/gtao_edge
  "$PY" $T/table.py $T/{bitmask,exact,linear,backface,backface_edge,edge}/params.json --gtao $T/gtao/params.json
  rm -rf "$CACHE"/targets_truths  # the truths' cache key does not name the edge_aware cell rule: render them afresh
  TORCH_AO_CACHE=$CACHE "$PY" $T/split_error.py $T/{backface,backface_edge}/params.json \
      --scenes sphere_on_plane,fence,floating,poles
}

meshes() {  # four assimp-testmodels meshes: two training views and one held-out view each
  "$PY" benchmarks/fit_meshes.py "$MODELS"/OBJ/regr01.obj "$MODELS"/glTF2/ClearCoat-glTF/ClearCoatTest.gltf \
      "$MODELS"/STL/sphereWithHole.stl "$MODELS"/OBJ/box_longline.obj --cache "$CACHE"/meshes_fit --out $T/meshes
}

bench() {  # error against run time with the first set's fits as rows (needs `first`)
  local out; out=$(mktemp -d)
  "$PY" -m torch_ao.cli bench --quick --no-backward --max-distance 0.5 --cache "$CACHE" \
      --fitted $T/{bitmask,exact,gtao}/params.json --out "$out"
  cp "$out"/bench.md $T/bench_quick_R0.5.md
}

case "${1:-all}" in
  views2x3|first|meshes|bench) "$1" ;;
  all) views2x3; first; meshes; bench ;;
  *) echo "regenerate.sh: unknown part '$1'; expected views2x3, first, meshes, bench or all" >&2; exit 2 ;;
esac

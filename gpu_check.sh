# one lease: the Warp kernels on CUDA (tests), the front-end and tracking benches, the Hamlyn pair, a demo
source /tmp/site/env.sh
python3 -m pip install -q --no-deps --no-build-isolation -e . > /dev/null 2>&1
nvidia-smi --query-gpu=name --format=csv,noheader
export LAPRECO_TEST_DEVICE=cuda:0
timeout 240 python3 -m pytest -q -x tests/test_frontend_warp.py tests/test_frontend_epipolar.py -p no:cacheprovider 2>&1 | tail -4
python3 - <<'PY' 2>&1 | grep -v "^Module\|^Warp\|^   "
import json, warp as wp
from lapreco_hil.bench import frontend
r = frontend.run("cuda:0", [(1920, 1080), (3840, 2160)], [2000, 8000][:1], frames=60, warmup=10)
print(json.dumps(r, default=str)[:3000])
PY
timeout 300 lapreco bench tracking --tracker warp --device cuda --predict both --speeds 0,20,40,60,80 --frames 16 --json $OUT/bt_cuda.json 2>&1 | grep -v "^Module\|^Warp" | tail -30
python3 - <<'PY' 2>&1 | grep -v "^Module\|^Warp\|^   "
import subprocess, sys, tempfile
from pathlib import Path
sys.path.insert(0, "tests")
import test_real_stereo_pair as t
from lapreco_hil.app.replay import run_replay
d = Path(tempfile.mkdtemp())
t.write_two_frame_session(d / "v1")
(d / "s.py").write_text(t._documented_v2_script())
subprocess.run([sys.executable, str(d / "s.py"), str(t.HAMLYN), str(d / "v2")], check=True)
for name in ("v1", "v2"):
    r = run_replay(str(d / name), str(d / ("out" + name)), tracker="warp", device="cuda:0", progress=False)
    print("hamlyn", name, "warp cuda:", r["inliers"], r["reprojection"], r["funnel"])
PY
timeout 200 lapreco demo --sequential --tracker warp --device cuda --out /tmp/demo_cuda 2>&1 | tail -2

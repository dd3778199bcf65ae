"""The final build's fused points of the three rendered stereo pairs of dense_pair.py (the path of
tests/test_dense_two_view.py: DenseSurface.build_at of two views), against both views' true depths: points, and the
shares beyond 5 mm and 1 mm of the true surface. Session 20 (docs/dense.md, "Two views"); not part of the package."""
import importlib.util
from pathlib import Path

import numpy as np

TESTS = Path(__file__).resolve().parents[2] / "tests"
spec = importlib.util.spec_from_file_location("t2v", TESTS / "test_dense_two_view.py")
t = importlib.util.module_from_spec(spec)
spec.loader.exec_module(t)  # the test's renderer of a stereo pair

from lapreco_hil.config import PipelineConfig  # noqa: E402
from lapreco_hil.dense.surface import DenseSurface  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

for name, eye in (("liver", (0.01, 0.03, 0.075)), ("skull", (0.02, -0.01, 0.08)), ("liver", (-0.02, 0.0, 0.09))):
    camera, left, right, dl, dr, TL, TR = t._render_pair(name, eye)
    dense = DenseSurface(camera, PipelineConfig(), "cpu")
    dense.add_view(0, left, TL); dense.add_view(1, right, TR)
    res = dense.build_at({0: TL, 1: TR}, {0: t._range(dl), 1: t._range(dr)})
    K = camera.K
    clouds = []
    for d, T in ((dl, TL), (dr, TR)):
        v, u = np.nonzero(d > 0); z = d[v, u]
        X = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
        clouds.append((T[:3, :3] @ X).T + T[:3, 3])
    truth = np.vstack(clouds)
    dist = cKDTree(truth).query(res.points)[0]
    print(name, eye[2], "points", len(res.points), "beyond 5mm %.3f%%" % (100 * (dist > 5e-3).mean()), "beyond 1mm %.2f%%" % (100 * (dist > 1e-3).mean()), flush=True)

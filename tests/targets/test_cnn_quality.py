"""The shipped nets on held-out simulator frames, rendered at test time with a seed
never used in training (``HELDOUT_SEED_BASE``; training uses seed 0).

Thresholds: detector mAP50 >= 0.8 (mean over vehicle, pedestrian, obstacle of AP at
IoU 0.5; boxes >= 16 px tall and >= 30 % visible are evaluated, the rest ignored:
KITTI's moderate floor scaled to 240 rows, training/train.py), and vehicles, on which
the closed loop stops, AP50 >= 0.8 down to 8 px (a car 36 m away); steering mean absolute error against the expert <= 6 mrad and
95th percentile <= 20 mrad (training measured ~2-3 mrad and ~10 mrad on its own
validation split: targets/weights/MODEL_CARD.md).
"""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from hil.training import train  # noqa: E402

from hil.targets.cnn import models  # noqa: E402
from hil.training import dataset  # noqa: E402
from tests.conftest import ahead, ahead_results  # noqa: E402

N_FRAMES = 500


def heldout_samples() -> list[dataset.Sample]:
    """The held-out frames (rendering them is the fixture's work; a module-level
    function: a child process runs it, ahead, beside the tests before these)."""
    from hil.scenarios.gl import select_backend

    select_backend()
    return list(dataset.generate(seed=dataset.HELDOUT_SEED_BASE, n_frames=N_FRAMES, split=0))


ahead(__name__, "heldout", heldout_samples, [()])


@pytest.fixture(scope="module")
def heldout():
    torch.set_num_threads(2)
    (samples,) = ahead_results(__name__, "heldout")
    return train.prepare(samples)


@pytest.mark.slow
def test_detector_ap50_on_heldout_frames(heldout):
    det, _ = models.load("detector")
    res = train.evaluate_detector(det, heldout)
    print(f"held-out detector mAP50 {res['map50']:.3f}: "
          + ", ".join(f"{k} {v['ap50']:.3f} ({v['evaluated']} boxes)" for k, v in res["classes"].items()))
    assert set(res["classes"]) == {"vehicle", "pedestrian", "obstacle"}
    assert all(v["evaluated"] >= 15 for v in res["classes"].values())
    print("lower floors:", res["by_min_height"])
    assert res["map50"] >= 0.8
    assert res["by_min_height"]["8.0"]["vehicle"] >= 0.8


@pytest.mark.slow
def test_steering_error_on_heldout_frames(heldout):
    net, _ = models.load("steering")
    res = train.evaluate_steering(net, heldout)
    print(f"held-out steering error: mean {res['mae_rad'] * 1e3:.2f} mrad, p95 {res['p95_rad'] * 1e3:.2f} mrad, "
          f"near the centre {res['mae_near_centre_rad'] * 1e3:.2f} mrad (labels' spread {res['label_std_rad'] * 1e3:.1f})")
    assert res["mae_rad"] <= 0.006 and res["p95_rad"] <= 0.020


def test_heldout_seed_is_not_the_training_seed():
    meta = models.load("steering")[1]
    assert meta["seed"] != dataset.HELDOUT_SEED_BASE and meta["dataset"]["seed"] == meta["seed"]

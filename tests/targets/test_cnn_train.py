"""The CNN target's training side (training/dataset.py, training/train.py): seeded
data with sane labels, deterministic training, the AP metric, the ``hil train`` CLI."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from hil.training import train  # noqa: E402

from hil.training import dataset


def _box(cls: str, box: tuple[int, int, int, int], visible: float = 1.0) -> dataset.LabelBox:
    return dataset.LabelBox(cls, box, (box[2] - box[0]) * (box[3] - box[1]), visible, False, 20.0, 0.0)


@pytest.fixture(scope="module")
def frames() -> list[dataset.Sample]:
    from hil.scenarios.gl import select_backend

    select_backend()
    return list(dataset.generate(seed=123, n_frames=48))


def test_same_seed_same_frames(frames):
    again = list(dataset.generate(seed=123, n_frames=12))
    assert [s.jpeg for s in again] == [s.jpeg for s in frames[:12]]
    assert [s.label_json() for s in again] == [s.label_json() for s in frames[:12]]
    other = next(dataset.generate(seed=124, n_frames=1))
    assert other.jpeg != frames[0].jpeg


def test_labels_make_sense(frames):
    classes = set()
    for s in frames:
        assert abs(s.steering_rad) <= dataset.MAX_STEER_RAD and s.speed_mps >= 0
        for b in s.boxes:
            x0, y0, x1, y1 = b.box_px
            assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 240 and b.visible_px > 0
            classes.add(b.cls)
        # Pure pursuit on the lane centre: left of it (and not yawed back) means steer right.
        if abs(s.heading_err_rad) < 0.01 and abs(s.lateral_m) > 0.4:
            assert math.copysign(1, s.steering_rad) == -math.copysign(1, s.lateral_m), s.label_json()
    assert classes <= {"vehicle", "pedestrian", "obstacle"} and "vehicle" in classes


def test_split_round_trips_through_disk(frames, tmp_path):
    assert dataset.write_split(tmp_path / "s", iter(frames[:5])) == 5
    back = dataset.read_split(tmp_path / "s")
    assert [b.label_json() for b in back] == [f.label_json() for f in frames[:5]]
    assert [b.jpeg for b in back] == [f.jpeg for f in frames[:5]]


def test_detector_maps_put_the_centre_in_its_cell_and_flip_exactly():
    maps = train.detector_maps([_box("pedestrian", (101, 80, 108, 112))], 320, 240)
    # 320 -> 160 px, stride 4: centre (52.25, 48) det px -> cell (13, 12), offset (0.0625, 0).
    assert maps[1, 12, 13] == 1.0 and maps[7].sum() == 1.0 and maps[0].max() == 0.0
    assert maps[3, 12, 13] == pytest.approx(math.log(3.5)) and maps[4, 12, 13] == pytest.approx(math.log(16.0))
    assert maps[5, 12, 13] == pytest.approx(0.0625) and maps[6, 12, 13] == pytest.approx(0.0)
    mirrored = train.detector_maps([_box("pedestrian", (320 - 108, 80, 320 - 101, 112))], 320, 240)
    flipped = train._flip_maps(torch.from_numpy(maps)).numpy()
    assert np.allclose(flipped, mirrored, atol=1e-6)


def test_average_precision_rules():
    car, ped = _box("vehicle", (100, 100, 140, 130)), _box("pedestrian", (200, 100, 206, 104))  # ped: 4 px, ignored
    perfect = train.average_precision([[("vehicle", 0.9, (100, 100, 140, 130))]], [[car, ped]])
    assert perfect["map50"] == 1.0 and set(perfect["classes"]) == {"vehicle"}
    # A better-scored ghost halves the precision at full recall; detections on the
    # ignored pedestrian (or too small to count) change nothing.
    dets = [[("vehicle", 0.95, (10, 10, 50, 40)), ("vehicle", 0.9, (101, 100, 140, 130)),
             ("pedestrian", 0.99, (199, 100, 206, 105)), ("vehicle", 0.99, (300, 10, 303, 13))]]
    res = train.average_precision(dets, [[car, ped]])
    assert res["classes"]["vehicle"]["ap50"] == pytest.approx(0.5)
    missed = train.average_precision([[]], [[car]])
    assert missed["map50"] == 0.0


def test_training_is_deterministic(frames):
    data = train.prepare(frames[:32])
    torch.set_num_threads(2)

    def once() -> list:
        det, _ = train.train_detector(data, epochs=1, batch=16, seed=0, log=lambda _t: None)
        steer, _ = train.train_steering(data, epochs=1, batch=16, seed=0, log=lambda _t: None)
        return [t.clone() for t in (*det.state_dict().values(), *steer.state_dict().values())]

    torch.use_deterministic_algorithms(True)
    try:
        a, b = once(), once()
    finally:
        torch.use_deterministic_algorithms(False)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_hil_train_refuses_bad_counts(capsys):
    args = SimpleNamespace(seed=0, out=None, data=None, threads=2, train_frames=0, val_frames=10, det_epochs=1,
                           steer_epochs=1)
    assert train.cmd(args) == 2
    assert "--train-frames must be at least 1" in capsys.readouterr().err


def test_training_and_rendering_say_how_long_is_left(frames, tmp_path):
    # hil train runs for minutes: each epoch line and every tenth of the dataset says
    # what is done and the time left at the pace so far.
    data = train.prepare(frames[:16])
    lines: list[str] = []
    train.train_detector(data, epochs=3, batch=16, seed=0, log=lines.append)
    assert [ln.split(" loss ")[0] for ln in lines] == [f"detector: epoch {i}/3" for i in (1, 2, 3)]
    assert all(" left)" in ln for ln in lines[:2]) and lines[2].endswith(", done)"), lines
    lines.clear()
    dataset.build_dataset(tmp_path / "d", seed=1, n_train=10, n_val=5, log=lines.append)
    assert lines[0].startswith("dataset: 1 of 15 frames rendered (") and "left)" in lines[0]
    assert lines[-1].startswith("dataset: 15 of 15 frames rendered (") and lines[-1].endswith(", done)")


"""The Foxglove layout shipped as ``hil_configs/foxglove_layout.json``: per vehicle the
camera with truth (green) and AI (magenta) boxes, the 3D scene with true cubes and
the AI's spheres, latency plots, and the event log.

Built with foxglove-sdk's ``foxglove.layouts`` (needs the ``foxglove-sdk`` package);
``python -m hil.harness.record.foxglove_layout [--rig PRESET] [VEHICLE ...] > layout.json``
writes one for other vehicle names (default ``ego0``) and, with ``--rig`` (``front3``,
``surround6``), an image panel for each other camera of the rig as well
(``hil_configs/foxglove_layout_surround6.json`` is ``--rig surround6 ego0``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from hil.harness.record.rig_views import annotations_topic, calibration_topic, camera_topic


def build_layout(vehicles: Sequence[str] = ("ego0",), *, rig_cameras: Sequence[str] = ()) -> str:
    """The layout as JSON text (Foxglove: Layouts → Import from file);
    ``rig_cameras``: the names of a rig's cameras after camera 0, each a panel of its
    own beside camera 0's, with its truth and AI boxes.

    Raises:
        ImportError: foxglove-sdk is not installed.
        ValueError: no vehicle named.
    """
    import foxglove.layouts as fl

    if not vehicles:
        raise ValueError("name at least one vehicle for the layout")
    cameras = [fl.ImagePanel(title=f"{v} camera: truth green, AI magenta", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(
            image_topic=f"/{v}/camera", calibration_topic=f"/{v}/camera_info",
            annotations={f"/{v}/annotations": fl.ImageAnnotationSettings(visible=True)}, synchronize=False)))
        for v in vehicles]
    cameras += [fl.ImagePanel(title=f"{v} camera {c}", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic=camera_topic(v, c), calibration_topic=calibration_topic(v, c),
        annotations={annotations_topic(v, c): fl.ImageAnnotationSettings(visible=True)}, synchronize=False)))
        for v in vehicles for c in rig_cameras]
    three_d = fl.ThreeDeePanel(title="3D: true cubes, AI spheres", config=fl.ThreeDeeConfig(
        follow_tf=vehicles[0], fixed_frame="world",
        topics={"/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
                **{f"/{v}/estimate_scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True) for v in vehicles}}))
    plot = fl.PlotPanel(title="end-to-end latency (ms)", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"/{v}/latency.stages_ms.end_to_end", label=f"{v} end-to-end (ms)")
        for v in vehicles] + [fl.PlotSeries(value=f"/{v}/latency.stages_ms.inference", label=f"{v} inference (ms)")
                              for v in vehicles]
        + [fl.PlotSeries(value=f"/{vehicles[0]}/latency.deadline_ms", label="deadline (ms)", line_style="dashed",
                         color="#d62728")], show_legend=True))
    log = fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render="/log", show_name=True))
    cam_items = [fl.SplitItem(proportion=1, content=c) for c in cameras]
    content = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=3, content=fl.SplitContainer(direction="row", items=cam_items)),
            fl.SplitItem(proportion=2, content=plot)])),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=3, content=three_d), fl.SplitItem(proportion=2, content=log)]))])
    return fl.Layout(content=content).to_json()


def main(argv: Sequence[str] | None = None) -> None:
    from hil.harness.config.model import CameraConfig
    from hil.harness.config.rig import PRESETS

    p = argparse.ArgumentParser(prog="python -m hil.harness.record.foxglove_layout")
    p.add_argument("--rig", choices=PRESETS, default="front", help="the egos' camera rig (default: one camera)")
    p.add_argument("vehicles", nargs="*", default=["ego0"])
    a = p.parse_args(argv)
    names = [c.name for c in CameraConfig(rig=a.rig).cameras()[1:]]
    print(build_layout(a.vehicles, rig_cameras=names))


if __name__ == "__main__":
    main()

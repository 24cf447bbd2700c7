"""Run configuration: the schema of a ``hil_configs/*.yaml`` file (loading it:
``hil.harness.config.loading``).

Every model is frozen and forbids unknown keys, and every field has a default, so an
empty mapping ``{}`` is a complete config. Units are in the field names (``_s``
seconds, ``_m`` metres, ``_deg`` degrees, ``fps`` frames per second).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from enum import Enum
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from hil.adapters.transports import Transport  # how the harness reaches the AI target: one enum, one table
from hil.adapters.wire.protocol import FRAME_META_SIZE, MAX_PAYLOAD
from hil.harness.config.detector import CornerCaseSettings, DetectorSettings
from hil.harness.config.rig import MAX_RIG_CAMERAS, PRESETS, RigCamera, preset
from hil.harness.config.target import CanTargetConfig, ImpairConfig, Ros2TargetConfig, TcpTargetConfig, ZenohTargetConfig
from hil.harness.config.timing import TimingConfig
from hil.harness.config.types import MODEL_CONFIG, Float, Int

__all__ = [
    "CameraConfig", "Encoding", "LatencyConfig", "LatencyKind", "LatencyStage", "LockstepConfig", "Mode",
    "RecordingConfig", "RunConfig", "ScenarioConfig", "TargetConfig", "Transport", "TruthConfig",
]

FPS_MAX = 240.0
SEED_MAX = 2**63 - 1
PHYSICS_STEP_MAX_S = 0.05
_PERIOD_REL_TOL = 1e-9
_PERIOD_ERROR = "camera_period"
_RULE_ERROR = "cross_field_rule"  # ctx: loc (the field to blame), got
_GOT_MAX_CHARS = 60


_MODEL_CONFIG = MODEL_CONFIG


class Mode(str, Enum):
    """How the simulation paces itself against the target."""

    REALTIME = "realtime"  # wall-clock pace, never waits for the target
    LOCKSTEP = "lockstep"  # waits for each estimate: deterministic, for replay

    @property
    def judges_rate_floor(self) -> bool:
        """Whether a run of this mode judges the frame-rate floor: in real time only.
        A lockstep run sets its own pace (the harness waits for each answer and renders
        the next frame only then), so its estimates per wall-clock second measure the
        harness and the machine as much as the AI (16 vehicles on 2 cores: 7.6 a second,
        a floor anomaly for every AI); an answer it never got is a ``dropped_frame``
        there, a slow one a deadline miss."""
        return self is Mode.REALTIME


class Encoding(str, Enum):
    """How camera frames travel on the wire."""

    RAW = "raw"
    JPEG = "jpeg"


class ScenarioConfig(BaseModel):
    """Which registered scenario to build, and its parameters (units in the names)."""

    model_config = _MODEL_CONFIG

    name: str = "stopped_car"
    params: dict[str, Float] = Field(default_factory=dict)


class CameraConfig(BaseModel):
    """The ego vehicle's camera: image size, optics, rate, encoding and mount."""

    model_config = _MODEL_CONFIG

    width: Int = Field(320, ge=16, le=4096)
    height: Int = Field(240, ge=16, le=4096)
    fovy_deg: Float = Field(60.0, ge=10, le=170)
    fps: Float = Field(20.0, gt=0, le=FPS_MAX)
    encoding: Encoding = Encoding.JPEG
    jpeg_quality: Int = Field(85, ge=1, le=100)
    shadows: bool = False
    reflections: bool = False
    # Samples per pixel of the offscreen render's multisample anti-aliasing (MuJoCo's
    # visual/quality/offsamples; 4, its default, as before this setting). 0: none, thin
    # distant lines break into dashes, and software GL (llvmpipe) renders a 320x240
    # camera ~2x cheaper (bench/README, "Anti-aliasing"). The GL driver may draw more
    # samples than asked (llvmpipe draws 4 for any value above 0).
    antialias: Int = Field(4, ge=0, le=16)
    mount_height_m: Float = Field(1.3, ge=0.2, le=5)
    mount_forward_m: Float = Field(2.3, ge=-5, le=5)  # from the vehicle centre
    mount_lateral_m: Float = Field(0.0, ge=-3, le=3)  # left of the vehicle centre line
    pitch_deg: Float = Field(0.0, ge=-45, le=45)  # positive looks down
    yaw_deg: Float = Field(0.0, ge=-180, le=180)  # positive looks left
    # The cameras on each ego (harness/config/rig.py): a preset's name or a list.
    # "front" is this section's one camera, as before rigs.
    rig: str | list[RigCamera] = "front"

    @field_validator("rig", mode="before")
    @classmethod
    def _known_rig(cls, v: object) -> object:
        if isinstance(v, str) and v not in PRESETS:
            raise ValueError(f"a preset ({', '.join(PRESETS)}) or a list of cameras")
        if isinstance(v, list) and not 1 <= len(v) <= MAX_RIG_CAMERAS:
            raise ValueError(f"1 to {MAX_RIG_CAMERAS} cameras")
        return v

    def cameras(self) -> tuple[RigCamera, ...]:
        """The rig's cameras in camera order, with this section's size and field of
        view where a camera leaves them unset."""
        cams = (preset(self.rig, forward_m=self.mount_forward_m, lateral_m=self.mount_lateral_m,
                       height_m=self.mount_height_m, pitch_deg=self.pitch_deg, yaw_deg=self.yaw_deg,
                       fovy_deg=self.fovy_deg) if isinstance(self.rig, str) else tuple(self.rig))
        return tuple(c.model_copy(update={"fovy_deg": c.fovy_deg if c.fovy_deg is not None else self.fovy_deg,
                                          "width": c.width or self.width, "height": c.height or self.height})
                     for c in cams)


class TargetCommand(BaseModel):
    """One command, sent to every vehicle's target when sim time reaches ``at_s``."""

    model_config = _MODEL_CONFIG

    at_s: Float = Field(ge=0)
    command: str = Field(min_length=1, max_length=256)
    vehicle: str | None = None  # only this vehicle's target (default: all)


class TargetConfig(BaseModel):
    """The AI target: how to reach it, how to start it, how long to wait for it.

    ``"{python}"`` in ``command`` is replaced with ``sys.executable`` at launch;
    ``args`` are appended to ``command``.
    """

    model_config = _MODEL_CONFIG

    transport: Transport = Transport.LOCAL
    # local: the program to start (required). zenoh/can: optional, [] = the target
    # runs elsewhere; see harness/config/target.py for {vehicle_id} and {port}.
    command: list[str] = Field(default_factory=lambda: ["{python}", "-m", "hil.targets.cv_baseline"])
    args: list[str] = Field(default_factory=list)
    zenoh: ZenohTargetConfig = Field(default_factory=ZenohTargetConfig)
    can: CanTargetConfig = Field(default_factory=CanTargetConfig)
    tcp: TcpTargetConfig = Field(default_factory=TcpTargetConfig)
    ros2: Ros2TargetConfig = Field(default_factory=Ros2TargetConfig)
    impair: ImpairConfig = Field(default_factory=ImpairConfig)  # link faults in real time (config_target.py)
    # Commands for the targets' control software at given sim times, e.g.
    # [{at_s: 5.0, command: "swap detector cv"}] (targets announcing CAP_COMMANDS).
    commands: list[TargetCommand] = Field(default_factory=list)
    startup_timeout_s: Float = Field(15.0, gt=0, le=300)
    # No estimate within this after t0: the frame counts as dropped.
    estimate_timeout_s: Float = Field(0.5, gt=0, le=60)
    # One target process serves every vehicle (batched; harness/run/shared_target.py):
    # local or zenoh only.
    shared: bool = False
    # The HELLO target name a run accepts (prefix match), e.g. "cv_baseline" or
    # "cnn@cuda": a foreign target answering on the endpoint is refused (exit 2).
    expect_name: str | None = Field(None, min_length=1, max_length=256)


class RecordingConfig(BaseModel):
    """The recorder: its bounded queue (items), whether images are stored, and
    whether the run is also served live to Foxglove (``hil run --live [HOST:PORT]``: a
    WebSocket server on ``live_address``, default 127.0.0.1 and a free port, printed;
    see harness/record/live.py); a CAN run's bus traffic as ``run.blf`` or ``run.asc``
    beside ``run.mcap`` (``can_log``; see harness/record/can_log.py)."""

    model_config = _MODEL_CONFIG

    queue_size: Int = Field(4096, ge=16, le=1_000_000)
    images: bool = True
    live: bool = False
    can_log: Literal["blf", "asc", "none"] = "blf"
    # Also write rosbag2/ (ROS 2's bag: MCAP, CDR, metadata.yaml) after the run, for
    # `ros2 bag play` (harness/report/rosbag2.py); run.mcap is unchanged.
    rosbag2: bool = False
    live_address: str | None = Field(None, pattern=r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):[0-9]{1,5}$")


class TruthConfig(BaseModel):
    """Ground truth: the reference-state thresholds (rules in scenarios/ground_truth.py)
    and the per-camera visible boxes (a segmentation render per camera and frame)."""

    model_config = _MODEL_CONFIG

    comfort_decel_mps2: Float = Field(4.0, gt=0, le=15)
    stop_margin_m: Float = Field(5.0, ge=0, le=100)
    slow_headway_s: Float = Field(2.0, ge=0, le=20)
    slow_ttc_s: Float = Field(4.0, ge=0, le=60)
    visible_boxes: bool = True
    min_visible_px: Int = Field(1, ge=1, le=100_000)


class LatencyKind(str, Enum):
    """How lockstep delays the application of each estimate's control (sim time)."""

    NONE = "none"            # applied at the capture tick (no delay)
    CONSTANT = "constant"    # ms
    NORMAL = "normal"        # mean ms, std_ms; clipped to [min_ms, max_ms]
    LOGNORMAL = "lognormal"  # median ms, shape sigma; clipped to [min_ms, max_ms]
    RECORDED = "recorded"    # per frame, from a recorded run's pipeline records


class LatencyStage(str, Enum):
    """Which latency of a recorded run to replay."""

    SIM_APPLY = "sim_apply"    # sim_time_apply - sim_time: exactly what the sim saw
    TO_APPLY = "to_apply"      # t_apply - t0 (wall clock, times the recorded real-time factor)
    END_TO_END = "end_to_end"  # t0' - t0 (wall clock, times the recorded real-time factor)


class LatencyConfig(BaseModel):
    """A latency profile for lockstep replay (see harness/run/latency.py)."""

    model_config = _MODEL_CONFIG

    kind: LatencyKind = LatencyKind.NONE
    ms: Float = Field(100.0, ge=0, le=60_000)
    std_ms: Float = Field(20.0, ge=0, le=60_000)
    sigma: Float = Field(0.5, gt=0, le=5)
    min_ms: Float = Field(0.0, ge=0, le=60_000)
    max_ms: Float = Field(5_000.0, ge=0, le=60_000)
    path: str | None = None  # a recorded run's folder or its run.mcap
    stage: LatencyStage = LatencyStage.SIM_APPLY
    # Each frame's control is lost on the link with this probability (seeded per
    # vehicle and frame; constant/normal/lognormal profiles): a dropped frame.
    drop_prob: Float = Field(0.0, ge=0, le=1)
    # A camera of the rig, by name, on top of the profile: its frames' controls come
    # camera_ms later, and each is lost with camera_drop_prob (seeded per vehicle and
    # frame): a slow or lossy camera, as hil search draws one.
    camera_ms: dict[str, Annotated[Float, Field(ge=0, le=60_000)]] = Field(default_factory=dict)
    camera_drop_prob: dict[str, Annotated[Float, Field(ge=0, le=1)]] = Field(default_factory=dict)

    @property
    def active(self) -> bool:
        """Whether the profile delays or drops any control (else lockstep applies each at once)."""
        return (self.kind != LatencyKind.NONE or self.drop_prob > 0 or any(self.camera_ms.values())
                or any(self.camera_drop_prob.values()))


class CapturePhase(str, Enum):
    """When each vehicle's camera captures within the camera period (real time)."""

    SPREAD = "spread"    # vehicle i at i/N of the period: no capture burst
    ALIGNED = "aligned"  # every camera at the same instant (lockstep always is)


class EngineFaults(BaseModel):
    """Faults injected into the camera pipeline, to test what a run reports when its
    own cameras lag (as ``target.impair`` does for links): every ``render_delay_every``-th
    frame of each camera (1: every frame) is held ``render_delay_ms`` by its render
    worker after rendering, before ``t0`` is stamped, as a slow renderer would."""

    model_config = _MODEL_CONFIG

    render_delay_ms: Float = Field(0.0, ge=0, le=10_000)
    render_delay_every: Int = Field(1, ge=1, le=1_000_000)
    # The run process (and each shard process) stops reading the physics's ring this
    # long, once, half a second into the run, as a stuck consumer would: the physics
    # must not wait for it.
    stall_run_ms: Float = Field(0.0, ge=0, le=60_000)
    # This camera of the rig (its name) never triggers, as a camera whose frames fail:
    # its frame ids in each frame set stay unused (PROTOCOL.md 4.2.1).
    drop_camera: str | None = None
    # The render worker fails (raises) on this frame of each camera (1: the first; 0:
    # never), as a renderer that crashes would: the run ends early, saying why.
    render_fail_at_frame: Int = Field(0, ge=0, le=1_000_000_000)


class EngineConfig(BaseModel):
    """The run's processes: physics pacing and the render pool (harness/engine).

    Real time is judged on two paths: a physics step starting more than
    ``late_tolerance_ms`` after its due instant is late (the default, 5 ms, is met by the
    physics process alone on a VM without real-time priority, where steps ran 1-3 ms
    late); a camera frame handed to its link more than ``frame_late_tolerance_ms`` after
    its camera instant (``t_tx - t_state``) is late (default: one camera period, i.e.
    the frame is out before its camera's next instant)."""

    model_config = _MODEL_CONFIG

    render_workers: Int = Field(0, ge=0, le=256)  # 0: one per spare core, at most one per vehicle
    capture_phase: CapturePhase = CapturePhase.SPREAD
    late_tolerance_ms: Float = Field(5.0, gt=0, le=1000)  # a physics step later than this is late
    frame_late_tolerance_ms: Float | None = Field(None, gt=0, le=60_000)  # None: one camera period
    realtime_priority: Int = Field(10, ge=0, le=99)  # SCHED_FIFO for the physics process (0: don't ask)
    # Without SCHED_FIFO the physics asks for this nice value instead (allowed where
    # RLIMIT_NICE grants it); 0: don't.
    fallback_nice: Int = Field(-10, ge=-20, le=0)
    # "auto": with 4 or more cores the physics has the last core to itself (the
    # harness's other processes and the targets keep off it); a number: that core;
    # "none": no pinning.
    physics_cpu: str | int = "auto"
    ring_kib: Int = Field(4096, ge=1, le=1 << 20)  # each ring the physics writes into (KiB)
    # Processes the vehicles' work is cut into (links, timing analysis, detector,
    # recording's encoding): "auto" gives one per 16 vehicles or part of them, at most a
    # quarter of the cores, and 1 (the run process itself) for 16 or fewer; a number asks for that many
    # (at most one per vehicle). Transports can and mixed and shared targets keep
    # every vehicle in the run process.
    shards: str | int = "auto"
    # Before a real-time run's first step the render workers render their cameras this
    # many ms, so a GPU that idled while the targets started is awake for the first
    # frames; "auto": 300 where the workers render on a GPU, 0 on a software renderer.
    render_warm_ms: str | int = "auto"
    faults: EngineFaults = Field(default_factory=EngineFaults)

    @field_validator("physics_cpu", "shards", "render_warm_ms", mode="before")
    @classmethod
    def _auto_or_count(cls, v: object, info: ValidationInfo) -> object:
        words = ("auto", "none") if info.field_name == "physics_cpu" else ("auto",)
        low = 1 if info.field_name == "shards" else 0
        if v in words or (isinstance(v, int) and not isinstance(v, bool) and low <= v <= 4095):
            return v
        raise ValueError(f"{' or '.join(repr(w) for w in words)} or a whole number from {low}")


# The verdicts a run can fail on (hil.harness.vocab.verdict.CheckName, same values).
VerdictName = Literal["realtime", "deadline", "drop", "collision", "mismatch", "anomaly"]


class VerdictConfig(BaseModel):
    """What fails a run (``hil run --fail-on`` adds to ``fail_on``): each named check
    that fails makes ``hil run`` exit 3. A deadline check fails when more than
    ``deadline_miss_fraction`` of a vehicle's frames are over a stage budget, a drop
    check when more than ``drop_fraction`` of its frames got no estimate in time."""

    model_config = _MODEL_CONFIG

    fail_on: list[VerdictName] = Field(default_factory=list)
    deadline_miss_fraction: Float = Field(0.0, ge=0, le=1)
    drop_fraction: Float = Field(0.0, ge=0, le=1)


class LockstepConfig(BaseModel):
    """Lockstep-only settings."""

    model_config = _MODEL_CONFIG

    latency: LatencyConfig = Field(default_factory=LatencyConfig)


class RunConfig(BaseModel):
    """One run: pacing, duration, physics step, scenario, camera, target, recording.

    Raises ``pydantic.ValidationError`` when built directly; ``load_config`` and
    ``parse_config`` turn that into a one-line ``ConfigError``.
    """

    model_config = _MODEL_CONFIG

    name: str = Field("run", pattern=r"^[A-Za-z0-9_.-]+$")
    # At most a signed 64-bit integer: the corner-case index stores it as an SQLite INTEGER.
    seed: Int = Field(0, ge=0, le=SEED_MAX)
    mode: Mode = Mode.REALTIME
    duration_s: Float = Field(20.0, gt=0, le=86400)
    realtime_factor: Float = Field(1.0, gt=0, le=100)
    physics_step_s: Float = Field(0.002, gt=0, le=PHYSICS_STEP_MAX_S)
    scenario: ScenarioConfig = Field(default_factory=ScenarioConfig)
    camera: CameraConfig = Field(default_factory=CameraConfig)
    target: TargetConfig = Field(default_factory=TargetConfig)
    recording: RecordingConfig = Field(default_factory=RecordingConfig)
    truth: TruthConfig = Field(default_factory=TruthConfig)
    lockstep: LockstepConfig = Field(default_factory=LockstepConfig)
    timing: TimingConfig = Field(default_factory=TimingConfig)
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    corner_cases: CornerCaseSettings = Field(default_factory=CornerCaseSettings)
    engine: EngineConfig = Field(default_factory=EngineConfig)
    verdict: VerdictConfig = Field(default_factory=VerdictConfig)
    progress: bool = True

    @model_validator(mode="after")
    def _camera_period_fits_physics_step(self) -> RunConfig:
        fps, step = self.camera.fps, self.physics_step_s
        if not _period_fits(fps, step):
            raise PydanticCustomError(_PERIOD_ERROR, _period_message(fps, step), {"fps": fps})
        cam = self.camera
        if cam.encoding == Encoding.RAW and 3 * cam.width * cam.height + FRAME_META_SIZE > MAX_PAYLOAD:
            most = (MAX_PAYLOAD - FRAME_META_SIZE) // 3
            raise PydanticCustomError(_RULE_ERROR, f"a raw frame (3 bytes a pixel) within the wire's payload limit "
                                      f"of {MAX_PAYLOAD // 2**20} MiB, at most {most} pixels (e.g. 2560x2048), "
                                      f"but {cam.width}x{cam.height} needs {3 * cam.width * cam.height / 2**20:.1f} "
                                      f"MiB; use camera.encoding: jpeg or a smaller image",
                                      {"loc": ("camera", "width"), "got": cam.width})
        _check_rig(cam, self.physics_step_s)
        drop = self.engine.faults.drop_camera
        if drop is not None and drop not in [c.name for c in cam.cameras()]:
            raise PydanticCustomError(_RULE_ERROR, "the name of a camera of camera.rig: " + ", ".join(
                c.name for c in cam.cameras()), {"loc": ("engine", "faults", "drop_camera"), "got": drop})
        lat = self.lockstep.latency
        for group in ("camera_ms", "camera_drop_prob"):
            unknown = [n for n in getattr(lat, group) if n not in [c.name for c in cam.cameras()]]
            if unknown:
                raise PydanticCustomError(_RULE_ERROR, "the name of a camera of camera.rig: " + ", ".join(
                    c.name for c in cam.cameras()), {"loc": ("lockstep", "latency", group, unknown[0]),
                                                     "got": unknown[0]})
        if lat.active and self.mode != Mode.LOCKSTEP:
            raise PydanticCustomError(_RULE_ERROR, "mode: lockstep (a latency profile delays control in "
                                      "lockstep only; in realtime the target's own latency applies)",
                                      {"loc": ("lockstep", "latency", "kind"), "got": lat.kind.value})
        if lat.kind == LatencyKind.RECORDED:
            if not lat.path:
                raise PydanticCustomError(_RULE_ERROR, "a recorded run's folder or run.mcap in "
                                          "lockstep.latency.path", {"loc": ("lockstep", "latency", "path"),
                                                                    "got": None})
            if not (Path(lat.path).is_file() or (Path(lat.path) / "run.mcap").is_file()):
                raise PydanticCustomError(_RULE_ERROR, "an existing run.mcap or a run folder holding one",
                                          {"loc": ("lockstep", "latency", "path"), "got": lat.path})
        if lat.min_ms > lat.max_ms:
            raise PydanticCustomError(_RULE_ERROR, f"at most max_ms ({lat.max_ms:g})",
                                      {"loc": ("lockstep", "latency", "min_ms"), "got": lat.min_ms})
        if self.target.zenoh.auth is not None and self.target.transport not in (Transport.ZENOH, Transport.MIXED):
            raise PydanticCustomError(_RULE_ERROR, "no auth section: user/password authentication is offered "
                                      "for transport: zenoh or mixed", {"loc": ("target", "zenoh", "auth"),
                                                               "got": self.target.transport.value})
        if self.target.shared and self.target.transport not in (Transport.LOCAL, Transport.ZENOH):
            raise PydanticCustomError(_RULE_ERROR, "shared: false, or transport local or zenoh (a shared "
                                      "target serves all vehicles over those)",
                                      {"loc": ("target", "shared"), "got": self.target.transport.value})
        if self.target.transport == Transport.LOCAL and not self.target.command:
            raise PydanticCustomError(_RULE_ERROR, "the program to start: the local transport runs the "
                                      "target as a child process", {"loc": ("target", "command"), "got": []})
        return self

    @property
    def camera_period_steps(self) -> int:
        """Physics steps per camera frame (the camera period is a whole multiple)."""
        return round(1.0 / (self.camera.fps * self.physics_step_s))

    @property
    def rig_offset_steps(self) -> tuple[int, ...]:
        """Each rig camera's trigger offset after camera 0, in physics steps."""
        return tuple(round(c.offset_ms / (self.physics_step_s * 1e3)) for c in self.camera.cameras())

    @property
    def frame_late_tolerance_ns(self) -> int:
        """A frame handed to its link later than this after its camera instant is late
        (``engine.frame_late_tolerance_ms``; default one camera period)."""
        ms = self.engine.frame_late_tolerance_ms
        return int(ms * 1e6) if ms is not None else round(1e9 / self.camera.fps)


# --- camera period / physics step -----------------------------------------------


def _check_rig(cam: CameraConfig, step_s: float) -> None:
    """Names unique; each camera's frame within the wire's limit; trigger offsets whole
    physics steps, within the camera period and not decreasing in camera order (a
    set's frames go out in camera order)."""
    cams = cam.cameras()
    period_ms = 1e3 / cam.fps
    names: set[str] = set()
    for k, c in enumerate(cams):
        loc = ("camera", "rig", k)
        if c.name in names:
            raise PydanticCustomError(_RULE_ERROR, "a name no other camera of the rig has",
                                      {"loc": (*loc, "name"), "got": c.name})
        names.add(c.name)
        w, h = c.width or cam.width, c.height or cam.height
        if cam.encoding == Encoding.RAW and 3 * w * h + FRAME_META_SIZE > MAX_PAYLOAD:
            raise PydanticCustomError(_RULE_ERROR, "a raw frame within the wire's payload limit; use "
                                      "camera.encoding: jpeg or a smaller image", {"loc": (*loc, "width"), "got": w})
        steps = c.offset_ms / (step_s * 1e3)
        if not math.isclose(steps, round(steps), rel_tol=1e-9, abs_tol=1e-9):
            raise PydanticCustomError(_RULE_ERROR, f"a whole number of physics steps ({step_s * 1e3:g} ms)",
                                      {"loc": (*loc, "offset_ms"), "got": c.offset_ms})
        if c.offset_ms >= period_ms:
            raise PydanticCustomError(_RULE_ERROR, f"below the camera period ({period_ms:g} ms)",
                                      {"loc": (*loc, "offset_ms"), "got": c.offset_ms})
        if k and c.offset_ms < cams[k - 1].offset_ms:
            raise PydanticCustomError(_RULE_ERROR, f"at least camera {k - 1}'s ({cams[k - 1].offset_ms:g}): "
                                      "offsets do not decrease in camera order",
                                      {"loc": (*loc, "offset_ms"), "got": c.offset_ms})



def _period_fits(fps: float, step_s: float, *, rel_tol: float = _PERIOD_REL_TOL) -> bool:
    steps = 1.0 / (fps * step_s)
    return round(steps) >= 1 and math.isclose(steps, round(steps), rel_tol=rel_tol)


def _shortest(value: float, ok: Callable[[float], bool]) -> str:
    """Fewest decimals of ``value`` that still pass ``ok`` (so a suggestion works)."""
    for decimals in range(18):
        text = f"{value:.{decimals}f}"
        if float(text) > 0 and ok(float(text)):
            return text
    return repr(value)


def _period_message(fps: float, step_s: float) -> str:
    steps = 1.0 / (fps * step_s)
    period_s = 1.0 / fps
    # Suggestions are rounded, but 10x inside the tolerance so none is borderline.
    tight = _PERIOD_REL_TOL / 10

    def fps_text(k: int) -> str:
        return _shortest(
            1.0 / (k * step_s),
            lambda v: v <= FPS_MAX
            and round(1.0 / (v * step_s)) == k
            and _period_fits(v, step_s, rel_tol=tight),
        )

    def step_text(m: int) -> str:
        return _shortest(
            period_s / m,
            lambda v: v <= PHYSICS_STEP_MAX_S
            and round(1.0 / (fps * v)) == m
            and _period_fits(fps, v, rel_tol=tight),
        )

    # fps = 1/(k*step) nearest the asked one, within the fps bound.
    k_min = max(1, math.ceil(1.0 / (FPS_MAX * step_s) - 1e-9))
    ks = range(max(k_min, math.floor(steps) - 6), max(k_min, math.floor(steps)) + 8)
    near_ks = sorted(ks, key=lambda k: abs(1.0 / (k * step_s) - fps))[:6]
    # physics step = period/m nearest the asked one, within the step bound.
    ms = [m for m in range(max(1, math.floor(steps) - 2), math.floor(steps) + 4)
          if period_s / m <= PHYSICS_STEP_MAX_S]
    near_ms = sorted(ms, key=lambda m: abs(period_s / m - step_s))[:3]
    message = (
        f"a camera period (1/fps = {period_s * 1e3:.6g} ms) that is a whole multiple "
        f"of physics_step_s ({step_s * 1e3:.6g} ms), but it is {steps:.6g} steps; "
        f"with physics_step_s {step_s:g} use camera.fps one of "
        + ", ".join(fps_text(k) for k in sorted(near_ks))
    )
    if near_ms:
        message += f"; or with camera.fps {fps:g} use physics_step_s one of " + ", ".join(
            step_text(m) for m in sorted(near_ms)
        )
    return message

"""``python -m hil.targets.cnn`` / ``hil target cnn``: the CNN target's command line.

Serves ``CnnTarget`` through the target SDK: one vehicle (``sdk.serve``), or a
fleet batched (``--shared``, or started by the harness with ``target.shared``:
``hil.adapters.batching.serve_batched``), whose batch log gets each batch's parts
(``decode_ns, nets_ns, post_ns``). Exit 2, with one line, for a bad option, missing
weights, an unusable device or transport.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from hil.targets.cnn import commands
from hil.targets.cnn.decision import Policy
from hil.targets.cnn.target import PARTS, CnnTarget, Serving


def _parser(prog: str) -> argparse.ArgumentParser:
    from hil.adapters.sdk import TargetArgumentParser

    p = TargetArgumentParser(prog=prog, description="The two-CNN driving AI served over the target SDK.")
    p.add_argument("--detector", choices=commands.MODELS, default="cnn", help="object detector to start with")
    p.add_argument("--steering", choices=commands.MODELS, default="cnn", help="steering model to start with")
    p.add_argument("--cruise-speed", type=float, default=10.0, help="speed to hold when the lane is clear (m/s)")
    p.add_argument("--det-confidence", type=float, default=Policy.det_confidence,
                   help="report and act on detections at or above this confidence")
    p.add_argument("--det-uncertain", type=float, default=Policy.det_uncertain,
                   help="detections from here up to --det-confidence are uncertain (baseline consulted)")
    p.add_argument("--steer-error-max", type=float, default=None,
                   help="steering CNN's own error estimate (rad) above which it is overridden "
                        "(default: calibrated at training, in the weights' metadata)")
    p.add_argument("--weights", type=Path, default=None, help="folder with detector.pt and steering.pt "
                   "(default: the shipped weights)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: one core)")
    p.add_argument("--name", default="cnn", help="target name reported in HELLO (with @device (its name) added)")
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N or auto (CUDA when available)")
    s = p.add_argument_group("speed (hil.targets.cnn.accel, hil.targets.cnn.frontend)")
    s.add_argument("--decode-workers", default="0",
                   help="decode and preprocess a batch's frames on N workers (0: in this process; auto: measure "
                        "at start, one per core when they decode a batch >= 20%% faster; shared targets only)")
    s.add_argument("--decode-pool", choices=("process", "thread"), default="process",
                   help="the workers are processes (default) or threads of this process")
    s.add_argument("--precision", default="auto",
                   help="the nets' precision: auto (fp32 on the CPU, fp16 on CUDA), fp32, fp16 or bf16")
    s.add_argument("--preprocess", choices=("cpu", "device"), default="cpu",
                   help="resize and colour-convert with OpenCV on the CPU (default) or on the device "
                        "(whole decoded frames go there; JPEG decoded by nvJPEG when torchvision imports)")
    s.add_argument("--cuda-graphs", action=argparse.BooleanOptionalAction, default=True,
                   help="on CUDA, run each net as a CUDA graph per batch size bucket")
    g = p.add_argument_group("shared target (one process serves many vehicles, frames batched)")
    g.add_argument("--shared", action="store_true",
                   help="zenoh: serve the keys of each of --vehicles on one session (local: implied when the "
                        "harness starts the target with target.shared: true, ignored otherwise)")
    g.add_argument("--vehicles", default="1", help="zenoh: a count N (vehicles 0..N-1) or ids, e.g. 0,2,3")
    g.add_argument("--batch-window-ms", type=float, default=2.0,
                   help="longest a frame waits for other vehicles' frames before its batch runs (ms)")
    g.add_argument("--max-batch", type=int, default=16, help="most frames per batch")
    g.add_argument("--batch-log", default=None,
                   help="CSV of every frame's batch (default: $HIL_BATCH_LOG, set by the harness)")
    return p


def main(argv: Sequence[str] | None = None, *, prog: str = "python -m hil.targets.cnn") -> int:
    """Serve the CNN target through the target SDK; 2 when an option is bad, the
    transport is unusable (started by hand rather than by the harness) or the
    weights are missing."""
    from hil.adapters.batching import started_shared
    from hil.adapters.sdk import add_transport_args
    from hil.targets.cnn.frontend import parse_workers

    p = _parser(prog)
    add_transport_args(p)
    a = p.parse_args(argv)
    # local: shared exactly when the harness started it so (target.shared), whatever
    # --shared says, so one config's args serve both placements; zenoh: --shared.
    shared = started_shared() if a.transport == "local" else a.shared
    try:
        import torch

        if a.batch_window_ms < 0 or a.max_batch < 1:
            raise ValueError(f"--batch-window-ms {a.batch_window_ms:g} / --max-batch {a.max_batch}: "
                             "expected a window >= 0 and batches of >= 1")
        torch.set_num_threads(max(1, a.threads))
        serving = Serving(decode_workers=parse_workers(a.decode_workers), decode_pool=a.decode_pool,
                          max_batch=a.max_batch, precision=a.precision, preprocess=a.preprocess,
                          cuda_graphs=a.cuda_graphs, batched=shared)
        target = CnnTarget(detector=a.detector, steering=a.steering, cruise_speed_mps=a.cruise_speed,
                           weights_dir=a.weights, policy=Policy(det_confidence=a.det_confidence,
                                                                det_uncertain=a.det_uncertain),
                           device=a.device, serving=serving)
    except (FileNotFoundError, ValueError, ImportError, RuntimeError) as err:
        print(f"cnn: {err}", file=sys.stderr)
        return 2
    try:
        steer_max = a.steer_error_max or float(target.steer_meta.get("steer_error_max_rad",
                                                                     Policy.steer_error_max_rad))
        target.policy = Policy(det_confidence=a.det_confidence, det_uncertain=a.det_uncertain,
                               steer_error_max_rad=steer_max)
        return _serve(a, target, shared=shared)
    finally:
        print(f"cnn: {target.status()}", file=sys.stderr, flush=True)
        target.close()


class _Terminated(BaseException):
    """SIGTERM in a shared local target: leave serving through every ``finally``."""


def _terminate(*_: object) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends it where it stands
    raise _Terminated


def _serve(a: argparse.Namespace, target: CnnTarget, *, shared: bool) -> int:
    import torch

    from hil.adapters.sdk import serve, transport_options
    from hil.common.errors import HilError
    from hil.targets.cnn.device import hello_name

    name = hello_name(a.name, target.device, detail=target.device_name)
    print(f"cnn: device {target.device} ({target.device_name}), torch threads {torch.get_num_threads()}, "
          + ", ".join(f"{k} {v}" for k, v in target.speed().items()), file=sys.stderr, flush=True)
    try:
        if shared:
            from hil.adapters.batching import ConfigError, parse_vehicles, serve_batched

            try:
                vehicles = parse_vehicles(a.vehicles)
            except ValueError as err:
                print(f"cnn: {err}", file=sys.stderr)
                return 2
            if a.transport == "local" and threading.current_thread() is threading.main_thread():
                # The shared local transport's loop keeps SIGTERM's default (the process
                # dies where it stands): leave through the finally blocks instead, so the
                # scheduler finishes its batch, the batch log closes and the decode
                # workers are told to go (the Zenoh one stops on SIGTERM itself).
                signal.signal(signal.SIGTERM, _terminate)
            try:
                serve_batched(target.infer_batch, target_name=name, transport=a.transport, on_command=target.command,
                              window_ns=int(a.batch_window_ms * 1e6), max_batch=a.max_batch, vehicles=vehicles,
                              batch_log=a.batch_log, batch_parts=(PARTS, lambda: target.last_parts_ns),
                              **transport_options(a))
            except ConfigError as err:
                print(f"cnn: {err}", file=sys.stderr)
                return 2
            except _Terminated:
                print("cnn: SIGTERM: stopping", file=sys.stderr, flush=True)
        else:
            serve(target.infer, target_name=name, transport=a.transport, on_command=target.command,
                  **transport_options(a))
    except HilError as err:  # an unusable transport, a port in use: one line
        print(f"cnn: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    return 0

"""The main job end to end: bag -> bag_player -> sysid_node -> ~/identify -> figures.

``make run`` calls this. It generates the robot-arm bag (if missing), starts
``sysid_node`` and ``bag_player`` as separate processes, waits for the replay,
calls ``~/identify``, prints the model and its validation, writes the figures
and the model document, stops its processes and exits 0 (non-zero with one
error line if any step fails). ROS traffic stays on this machine
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) in its own ``ROS_DOMAIN_ID``.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["main", "stop_process"]


class PipelineError(RuntimeError):
    """A step of the pipeline failed."""


def _ros_env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def stop_process(proc: subprocess.Popen | None, timeout: float = 10.0) -> None:
    """Interrupt a child process (SIGINT, as Ctrl-C), kill it if it does not end."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def run(args) -> int:
    """Run the pipeline; raises PipelineError on a failed step."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag, signals = _bag(args)
    env = _ros_env(args.domain)
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")})
    node_log = open(out / "sysid_node.log", "w")
    node_proc = None
    import rclpy
    from rclpy.node import Node

    rclpy.init()
    client = Node("spm_sysid_pipeline")
    try:
        node_proc = _start_node(client, args, out, env, node_log)
        _replay(client, args, bag, env, expected=len(signals.y))
        doc, doc_sim = _identify_both(client, out)
    finally:
        stop_process(node_proc)
        node_log.close()
        client.destroy_node()
        rclpy.shutdown()
    print("[7/7] models (published on /spm_sysid/model), validated on the replayed data:")
    for name, document, path in (("prediction", doc, out / "model.json"),
                                 ("simulation", doc_sim, out / "model_simulation.json")):
        _show_model(name, document, path, signals, out)
    return 0


def _bag(args):
    """The bag (written from the data unless it exists) and its signals as read back."""
    from ..core.io.bagio import read_bag_signals, write_io_bag
    from ..core.record import DataSpec, load_record

    bag = Path(args.bag)
    if args.force_bag or not (bag / "metadata.yaml").exists():
        record = load_record(DataSpec.from_values({}, data=args.data))
        write_io_bag(bag, record.u, record.y, rate_hz=args.bag_rate, overwrite=True)
        print(f"[1/7] wrote bag {bag} from {record.source} ({len(record)} samples per topic)")
    else:
        print(f"[1/7] using bag {bag}")
    return bag, read_bag_signals(bag)


def _start_node(client, args, out: Path, env: dict, node_log) -> subprocess.Popen:
    """sysid_node in its own process, once its service and its worker are up."""
    from std_srvs.srv import Trigger

    from ..ros.client import wait_for_buffer

    node_proc = subprocess.Popen(
        [sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
         "-p", f"criterion:={args.criterion}", "-p", f"seed:={args.seed}",
         "-p", f"model_path:={(out / 'model.json').resolve()}"],
        stdout=node_log, stderr=subprocess.STDOUT, env=env)
    print(f"[2/7] started sysid_node (pid {node_proc.pid}, ROS_DOMAIN_ID {args.domain}, "
          f"log {out / 'sysid_node.log'})")
    ident = client.create_client(Trigger, "/spm_sysid/identify")
    ready = ident.wait_for_service(timeout_sec=30.0)
    client.destroy_client(ident)
    if not ready:
        stop_process(node_proc)
        raise PipelineError("sysid_node did not offer /spm_sysid/identify within 30 s")
    # Start the replay only once the node is fully up (its worker process too): a
    # volatile subscriber misses what is sent before discovery completes on its side.
    if not wait_for_buffer(client, lambda kv: kv.get("worker_ready") == "True", 60.0):
        stop_process(node_proc)
        raise PipelineError("sysid_node published no diagnostics within 60 s")
    return node_proc


def _replay(client, args, bag: Path, env: dict, *, expected: int) -> None:
    """The bag played onto the node's topics; every sample must reach its buffer."""
    from ..ros.client import wait_for_buffer

    t0 = time.monotonic()
    player = subprocess.run(
        [sys.executable, "-m", "spm_sysid.ros.bag_player", "--ros-args",
         "-p", f"bag:={bag}", "-p", f"rate:={args.rate}", "-p", "wait_for_subscribers:=1"],
        capture_output=True, text=True, env=env, timeout=600)
    if player.returncode != 0:
        raise PipelineError(f"bag_player failed: {player.stderr.strip()}")
    print(f"[3/7] replayed {bag} at {args.rate:g}x in {time.monotonic() - t0:.1f} s")
    have = int(wait_for_buffer(client, lambda kv: int(kv["samples"]) >= expected,
                               15.0).get("samples", 0))
    if have < expected:
        raise PipelineError(f"the node buffered {have} of {expected} samples")
    print(f"[4/7] sysid_node buffered {have} paired samples")


def _identify_both(client, out: Path) -> tuple[dict, dict]:
    """~/identify with the paper's focus, then with focus simulation: the two documents."""
    from ..ros.client import call_trigger, set_parameters, wait_for_model

    ok, message = call_trigger(client, "/spm_sysid/identify", timeout=600.0)
    if not ok:
        raise PipelineError(f"~/identify refused: {message}")
    print(f"[5/7] ~/identify (focus prediction, the paper's): {message}")
    doc = wait_for_model(client, "/spm_sysid/model")
    if doc is None:
        raise PipelineError("no model on /spm_sysid/model")
    # the same data, the model chosen and fitted for free-run simulation
    set_parameters(client, "/spm_sysid", focus="simulation",
                   model_path=str((out / "model_simulation.json").resolve()))
    ok, message = call_trigger(client, "/spm_sysid/identify", timeout=600.0)
    if not ok:
        raise PipelineError(f"~/identify (focus simulation) refused: {message}")
    print(f"[6/7] ~/identify (focus simulation): {message}")
    doc_sim = wait_for_model(client, "/spm_sysid/model")
    if doc_sim is None or doc_sim.get("metadata", {}).get("focus") != "simulation":
        raise PipelineError("no simulation-focused model on /spm_sysid/model")
    return doc, doc_sim


def _show_model(name: str, document: dict, path: Path, signals, out: Path) -> None:
    """One published model: the same as saved, validated on the replayed data, with figures."""
    from ..core.model.narx import NarxModel
    from ..core.validate.validation import validate_model
    from ..tools.plots import write_model_figures

    model = NarxModel.from_dict(document)  # the node saved it (model_path)
    if NarxModel.load(path).coefficients.tolist() != model.coefficients.tolist():
        raise PipelineError(f"{path} differs from the published model")
    report = validate_model(model, signals.u, signals.y)
    stem = "model" if name == "prediction" else "model_simulation"
    figures = write_model_figures(report, out / "figures", stem, model=model)
    free = report.free_run_metrics
    print(f"  focus {name}: {model.equation()}")
    what = " (of the free-run error)" if name == "simulation" else ""
    print(f"  {model.criterion.upper()}{what} = {model.criterion_value:.2f}, "
          f"{len(model.terms)} terms, one-step MSE "
          f"{model.mse:.4e}, free-run fit "
          + (f"{free['fit_percent']:.1f} %" if free["diverged_at"] is None
             else f"DIVERGED at sample {free['diverged_at']}"))
    print("\n".join("    " + line for line in report.summary().splitlines()))
    print(f"    model document: {path}; figures: "
          f"{', '.join(str(p) for p in figures if p.suffix == '.png')}")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry (``python -m spm_sysid.apps.pipeline``)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/run", help="output directory (default out/run)")
    p.add_argument("--data", help="data file (default: the robot-arm data)")
    p.add_argument("--bag", default="bags/robot_arm", help="bag directory (default bags/robot_arm)")
    p.add_argument("--force-bag", action="store_true", help="regenerate the bag")
    p.add_argument("--bag-rate", type=float, default=100.0, help="nominal rate of a new bag, Hz")
    p.add_argument("--rate", type=float, default=10.0, help="replay speed factor (default 10)")
    p.add_argument("--criterion", default="aic")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--domain", type=int,
                   default=int(os.environ.get("ROS_DOMAIN_ID", "61") or 61),
                   help="ROS_DOMAIN_ID for this run (default: $ROS_DOMAIN_ID or 61)")
    args = p.parse_args(argv)
    try:
        return run(args)
    except (PipelineError, ValueError, OSError, TimeoutError,
            subprocess.TimeoutExpired) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

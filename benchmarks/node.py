"""Benchmark of sysid_node: ingest, identify latency, memory (``make bench-node``).

1. Ingest: a publisher process sends both topics at ``--rate`` Hz for
   ``--seconds`` s; compares what it published with what the node received.
2. Identify latency: the robot-arm data (1024 samples) in the buffer, then
   ``~/identify`` at the paper's settings ``--repeats`` times; median service
   round trip and the search's own time.
3. Memory: the node's resident memory empty and with a full buffer of
   ``--capacity`` pairs.
4. The Identify action: goal-to-result round trip at the paper's settings, and
   cancel latency (cancel request sent to the CANCELED result) of a long search.
5. Online: with the model identified and monitoring and tracking on, ingest
   at ``--rate`` Hz for ``--seconds`` s again: samples lost and the node's
   per-sample cost of prediction, monitor and tracker (from /diagnostics), and
   the node process's CPU time per sample (from /proc).
6. The live dashboard: the same online ingest on a second node started with
   ``dashboard_port``, while a client asks for ``/state.json`` four times a
   second as the page does: the node's CPU time per sample against step 5's
   (the issue's bound: at most 5 % more).

Prints figures; asserts nothing. ROS traffic stays on this machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

__all__ = ["main"]


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (/proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _online_ingest(client, pub, pid: int, rate: float, count: int) -> dict:
    """Ingest ``count`` pairs at ``rate`` with a model monitored: losses and costs."""
    from spm_sysid.ros.client import wait_for_buffer

    before = wait_for_buffer(client, lambda kv: True, 10)
    base = int(before["received_outputs"])
    online0 = wait_for_buffer(client, lambda kv: True, 10, status="model validity")
    cpu0 = _cpu_seconds(pid)
    pub(rate, count, "ramp")
    kv = wait_for_buffer(client, lambda kv: int(kv["received_outputs"]) >= base + count, 30)
    online = wait_for_buffer(client, lambda kv: int(kv["samples"]) >= int(
        online0.get("samples", 0)) + count, 30, status="model validity")
    cpu = _cpu_seconds(pid) - cpu0
    return {"inputs": int(kv["received_inputs"]) - base,
            "outputs": int(kv["received_outputs"]) - base,
            "lost": base + count - int(kv["received_outputs"]),
            "us_per_sample": float(online["microseconds_per_sample"]),
            "cpu_us_per_sample": 1e6 * cpu / count, "tracker": online.get("tracker_updates")}


def run(args) -> None:
    import rclpy
    from rclpy.node import Node

    from spm_sysid.ros.client import call_trigger, wait_for_buffer, wait_for_model

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(args.domain), PYTHONUNBUFFERED="1")
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")})
    node = subprocess.Popen([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                             "-p", f"buffer_capacity:={args.capacity}", "-p", "seed:=1",
                             "-p", "tracking:=true"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    rclpy.init()
    client = Node("bench_client")

    def pub(rate, count, data):
        p = subprocess.run([sys.executable, "-m", "spm_sysid.ros.signal_publisher",
                            str(rate), str(count), "--data", data, "--stamps", "wall"],
                           env=env, capture_output=True, text=True,
                           timeout=count / rate + 120)
        return json.loads(p.stdout.strip().splitlines()[-1])

    try:
        wait_for_buffer(client, lambda kv: kv.get("worker_ready") == "True", 60)
        rss_empty = _rss_mb(node.pid)

        # 1. ingest
        count = int(args.rate * args.seconds)
        sent = pub(args.rate, count, "ramp")
        kv = wait_for_buffer(client, lambda kv: int(kv["received_outputs"]) >= count, 30)
        lost_u = count - int(kv["received_inputs"])
        lost_y = count - int(kv["received_outputs"])
        print(f"ingest: {count} messages per topic at {args.rate:g} Hz over "
              f"{sent['seconds']:.1f} s (publisher late by >10 ms: {sent['late']}); node "
              f"received {kv['received_inputs']} inputs, {kv['received_outputs']} outputs, "
              f"paired {kv['paired']}; lost {lost_u} inputs, {lost_y} outputs")

        # 3. memory with a full buffer (fill the rest quickly)
        have = int(kv["samples"])
        if have < args.capacity:
            extra = args.capacity - have + 10
            target = int(kv["received_outputs"]) + extra
            t0 = time.monotonic()
            sent = pub(args.fill_rate, extra, "ramp")
            kv = wait_for_buffer(client, lambda kv: int(kv["received_outputs"]) >= target, 300)
            took = time.monotonic() - t0
            print(f"fill: {extra} pairs offered at {args.fill_rate:g} Hz (sent in "
                  f"{sent['seconds']:.1f} s), all received {took:.1f} s after starting the "
                  f"publisher process; lost {target - int(kv['received_outputs'])} outputs")
        rss_full = _rss_mb(node.pid)
        print(f"memory: node RSS {rss_empty:.1f} MB empty, {rss_full:.1f} MB with "
              f"{kv['samples']} of {args.capacity} pairs buffered (+{rss_full - rss_empty:.1f} MB;"
              f" the ring buffer's arrays are {3 * 8 * args.capacity / 1e6:.1f} MB)")

        # 2. identify latency on 1024 samples
        call_trigger(client, "/spm_sysid/clear", 30)
        pub(args.fill_rate, 1024, "robot_arm")
        wait_for_buffer(client, lambda kv: int(kv["samples"]) >= 1024, 60)
        rounds, searches = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ok, message = call_trigger(client, "/spm_sysid/identify", 300)
            rounds.append(time.perf_counter() - t0)
            if not ok:
                raise RuntimeError(message)
            doc = wait_for_model(client, "/spm_sysid/model")  # the seconds, from the document
            searches.append(float(doc["metadata"]["identify_seconds"]))
        print(f"identify latency (1024 samples, population 200, 300 generations, SPM 0.15, "
              f"AIC): median service round trip {statistics.median(rounds):.3f} s, median "
              f"identify+validate in the worker {statistics.median(searches):.3f} s "
              f"({args.repeats} calls)")
        # 4. the action: round trip, and cancel latency during a long search
        from spm_sysid.ros.client import identify_goal

        goals = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = identify_goal(client, "/spm_sysid/identify", timeout=300)
            goals.append(time.perf_counter() - t0)
            if out.result.error_code != 0:
                raise RuntimeError(out.result.message)
        cancels = [_cancel_latency(client) for _ in range(args.repeats)]
        print(f"identify action: median goal-to-result {statistics.median(goals):.3f} s; "
              f"cancel during a search: median {statistics.median(cancels):.3f} s, max "
              f"{max(cancels):.3f} s from the cancel request to the CANCELED result "
              f"({args.repeats} goals each)")
        # 5. online: ingest again with the model monitored and tracked
        plain = _online_ingest(client, pub, node.pid, args.rate, count)
        print(f"online (monitor and tracker on): {count} messages per topic at {args.rate:g} "
              f"Hz; node received {plain['inputs']} inputs, {plain['outputs']} outputs; lost "
              f"{plain['lost']}; per-sample cost (prediction, monitor, tracker) "
              f"{plain['us_per_sample']:.1f} us mean; node CPU "
              f"{plain['cpu_us_per_sample']:.1f} us per sample; tracker updates "
              f"{plain['tracker']}")
        if args.dashboard:  # the same name again: this node goes first
            node.send_signal(2)
            node.wait(20)
            _dashboard_cost(args, env, client, pub, count, plain)
    finally:
        node.send_signal(2)
        node.wait(20)
        client.destroy_node()
        rclpy.shutdown()


def _dashboard_cost(args, env, client, pub, count: int, plain: dict) -> None:
    """Step 6: the same online ingest on a node serving the dashboard, a page polling."""
    import threading
    import urllib.request

    from spm_sysid.ros.client import call_trigger, wait_for_buffer

    node = subprocess.Popen([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                             "-r", "__node:=spm_sysid", "-p", "seed:=1", "-p", "tracking:=true",
                             "-p", f"buffer_capacity:={args.capacity}",
                             "-p", f"dashboard_port:={args.dashboard_port}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    stop, polls, sizes = threading.Event(), [0], []

    def page() -> None:  # what the page does: /state.json every 250 ms
        url = f"http://127.0.0.1:{args.dashboard_port}/state.json"
        while not stop.wait(0.25):
            try:
                with urllib.request.urlopen(url, timeout=5) as r:
                    sizes.append(len(r.read()))
                polls[0] += 1
            except OSError:
                pass

    poller = threading.Thread(target=page, daemon=True)
    try:
        wait_for_buffer(client, lambda kv: kv.get("worker_ready") == "True", 60)
        pub(args.fill_rate, 1024, "robot_arm")
        wait_for_buffer(client, lambda kv: int(kv["samples"]) >= 1024, 60)
        ok, message = call_trigger(client, "/spm_sysid/identify", 300)
        if not ok:
            raise RuntimeError(message)
        poller.start()
        with_page = _online_ingest(client, pub, node.pid, args.rate, count)
        stop.set()
        poller.join(5)
        ratio = with_page["cpu_us_per_sample"] / plain["cpu_us_per_sample"]
        print(f"dashboard: the same ingest on a node serving the dashboard, /state.json asked "
              f"{polls[0]} times (4 a second; median {statistics.median(sizes or [0]) / 1e3:.0f}"
              f" kB): lost {with_page['lost']}; per-sample cost "
              f"{with_page['us_per_sample']:.1f} us; node CPU "
              f"{with_page['cpu_us_per_sample']:.1f} us per sample against "
              f"{plain['cpu_us_per_sample']:.1f} us without the dashboard: {ratio:.3f}x "
              f"({100 * (ratio - 1):+.1f} %)")
    finally:
        stop.set()
        node.send_signal(2)
        node.wait(20)


def _cancel_latency(client) -> float:
    """Seconds from a cancel request to the CANCELED result of a running search."""
    import rclpy
    from rclpy.action import ActionClient
    from spm_sysid_interfaces.action import Identify

    action = ActionClient(client, Identify, "/spm_sysid/identify")
    try:
        action.wait_for_server(timeout_sec=30)
        searching = []
        sent = action.send_goal_async(
            Identify.Goal(setting_names=["generations"], setting_values=["100000"]),
            feedback_callback=lambda m: searching.append(m.feedback.phase == "search"
                                                         and m.feedback.step >= 25))
        rclpy.spin_until_future_complete(client, sent, timeout_sec=30)
        handle = sent.result()
        while not any(searching):
            rclpy.spin_once(client, timeout_sec=0.1)
        result = handle.get_result_async()
        t0 = time.perf_counter()
        handle.cancel_goal_async()
        rclpy.spin_until_future_complete(client, result, timeout_sec=30)
        if result.result().result.error_code != Identify.Result.CANCELED:
            raise RuntimeError("the goal was not canceled: " + result.result().result.message)
        return time.perf_counter() - t0
    finally:
        action.destroy()


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(description="benchmark sysid_node")
    p.add_argument("--rate", type=float, default=1000.0)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--capacity", type=int, default=100_000)
    p.add_argument("--fill-rate", type=float, default=2000.0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--domain", type=int, default=64)
    p.add_argument("--no-dashboard", dest="dashboard", action="store_false",
                   help="skip step 6 (the dashboard's cost)")
    p.add_argument("--dashboard-port", type=int, default=8765)
    args = p.parse_args(argv)
    run(args)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

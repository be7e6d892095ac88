"""Failover under load: kill (or stall, then kill) one of two replicas while /plan is busy.

Starts router, services and gateway on free loopback ports with the shipped model, then, per
round: starts a second replica of --service, sends --requests /plan requests at --concurrency,
and part way through stops one replica (SIGSTOP for --stall-s, then SIGKILL; or SIGKILL only
with --stall-s 0). Prints one JSON line per round and a summary: every request should be
answered 200 while a replica lives.

    .venv/bin/python benchmarks/chaos_failover.py [--rounds 3] [--stall-s 0.3] [--service planner]
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.stack import Stack, StackConfig, free_port  # noqa: E402

BODY = {
    "task": "box_stacking",
    "start": {"state": {"stacks": [["red", "green"], ["blue"], ["yellow"]]}},
    "goal": {"state": {"stacks": [[], ["yellow", "green", "red"], ["blue"]]}},
    "include_images": False,
}


def replicas(http: httpx.Client, service: str) -> int:
    reply = http.get("/health")
    instances = reply.json()["services"][service]["instances"]
    return sum(i["task"] == "box_stacking" for i in instances)  # the task it asks for


def wait_for(predicate, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("timed out")
        time.sleep(0.2)


def one_round(stack: Stack, http: httpx.Client, args: argparse.Namespace, index: int) -> dict:
    name = f"{args.service}-chaos-{index}"
    victim = stack.start_service(args.service, name=name)
    wait_for(lambda: replicas(http, args.service) == 2)
    done = 0
    lock = threading.Lock()

    def post(_: int) -> tuple[int, float, str]:
        nonlocal done
        started = time.monotonic()
        reply = http.post("/plan", json=BODY)
        with lock:
            done += 1
        detail = "" if reply.status_code == 200 else reply.text[:120]
        return reply.status_code, time.monotonic() - started, detail

    def chaos() -> None:
        wait_for(lambda: done >= args.requests // 4, 30)
        if args.stall_s > 0:
            victim.send_signal(signal.SIGSTOP)
            time.sleep(args.stall_s)
        victim.kill()

    killer = threading.Thread(target=chaos)
    killer.start()
    with ThreadPoolExecutor(args.concurrency) as pool:
        answers = list(pool.map(post, range(args.requests)))
    killer.join()
    victim.wait(10)
    wait_for(lambda: replicas(http, args.service) == 1)
    failed = [detail for status, _, detail in answers if status != 200]
    return {
        "round": index,
        "by_status": dict(Counter(status for status, _, _ in answers)),
        "slowest_s": round(max(took for _, took, _ in answers), 3),
        "failures": failed[:3],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--service", default="planner", choices=["encoder", "planner", "apn", "sim"]
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--requests", type=int, default=80)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--stall-s", type=float, default=0.3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(port=free_port(), zenoh_port=free_port(), log_dir=Path(logs))
        with Stack(config) as stack, httpx.Client(base_url=config.url, timeout=30) as http:
            stack.start()
            stack.wait_healthy(90)
            rounds = []
            for index in range(args.rounds):
                rounds.append(one_round(stack, http, args, index))
                print(json.dumps(rounds[-1]), flush=True)
    total = sum((Counter(r["by_status"]) for r in rounds), Counter())
    summary = {"service": args.service, "stall_s": args.stall_s, "by_status": dict(total)}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()

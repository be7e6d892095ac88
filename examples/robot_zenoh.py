"""A robot over zenoh: ask `lsr/api/plan`, take the plan published on `lsr/robot/{id}/plan`.

    lsr up                                  # in another terminal: a router on :7447
    python examples/robot_zenoh.py [--connect tcp/127.0.0.1:7447] [--robot-id arm-1]
    python examples/robot_zenoh.py --start camera.png --goal goal.png

Only zenoh and the standard library: what a robot's own computer needs. A robot acts on the
first action, looks again and asks again until it is at the goal (`lsr robot` does that with a
simulated arm: `services/robot.py`). Under access control, load the robot's credentials file
(`python -m shared.zenoh_access ... --robots arm-1`) with `--config`.
"""

from __future__ import annotations

import argparse
import base64
import json
import queue
from pathlib import Path

import zenoh

START = {"state": {"stacks": [["red", "green"], ["blue"], ["yellow"]]}}
GOAL = {"state": {"stacks": [[], ["yellow", "green", "red"], ["blue"]]}}


def image(path: str) -> dict[str, str]:
    return {"image": base64.b64encode(Path(path).read_bytes()).decode()}


def session_config(connect: str, config_file: str | None) -> zenoh.Config:
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([connect]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447")
    parser.add_argument("--config", help="a zenoh config file: the robot's credentials")
    parser.add_argument("--robot-id", default="arm-1")
    parser.add_argument("--task", default="box_stacking")
    parser.add_argument("--start", help="a PNG/JPEG file (default: a box-stacking state)")
    parser.add_argument("--goal", help="a PNG/JPEG file (default: a box-stacking state)")
    args = parser.parse_args()

    body = {
        "task": args.task,
        "start": image(args.start) if args.start else START,
        "goal": image(args.goal) if args.goal else GOAL,
        "robot_id": args.robot_id,  # the plan is also published on lsr/robot/{id}/plan
        "include_images": False,
    }
    with zenoh.open(session_config(args.connect, args.config)) as session:
        published: queue.Queue[dict] = queue.Queue()
        subscriber = session.declare_subscriber(  # before asking: no plan goes unheard
            f"lsr/robot/{args.robot_id}/plan",
            lambda sample: published.put(json.loads(sample.payload.to_bytes())),
        )
        replies = session.get("lsr/api/plan", payload=json.dumps(body), timeout=10.0)
        reply = next(iter(replies), None)
        if reply is None or reply.ok is None:  # errors: {"status", "detail"} as REST gives
            raise SystemExit(f"refused: {reply.err.payload.to_string() if reply else 'no gateway'}")
        plan_id = json.loads(reply.ok.payload.to_bytes())["plan_id"]
        while (answer := published.get(timeout=10.0))["plan_id"] != plan_id:
            pass  # an older request's plan
        subscriber.undeclare()
        if not answer["plans"]:
            raise SystemExit(f"no plan: {answer['reason']}")
        plan = answer["plans"][0]
        print(f"[{args.robot_id}] plan {plan_id}: {len(plan['actions'])} actions")
        for step, action in enumerate(plan["actions"], 1):
            print(f"  {step}. {json.dumps(action)}")
        print(f"[{args.robot_id}] now execute action 1, look again and ask again")


if __name__ == "__main__":
    main()

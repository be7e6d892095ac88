"""Plan over REST from Python: a start and a goal in, visual action plans out.

    lsr up                                  # in another terminal: the stack on :8000
    python examples/plan_rest.py [--url http://127.0.0.1:8000] [--out plans/]
    python examples/plan_rest.py --start start.png --goal goal.png   # a camera's images

Only the standard library: copy it to any machine that reaches the gateway. With API keys on,
give `--api-key` (sent as `Authorization: Bearer`).
"""

from __future__ import annotations

import argparse
import base64
import json
import urllib.request
from pathlib import Path

START = {"state": {"stacks": [["red", "green"], ["blue"], ["yellow"]]}}
GOAL = {"state": {"stacks": [[], ["yellow", "green", "red"], ["blue"]]}}


def image(path: str) -> dict[str, str]:
    """An endpoint from a PNG or JPEG file: what a robot's camera saw."""
    return {"image": base64.b64encode(Path(path).read_bytes()).decode()}


def post(url: str, body: dict, api_key: str | None = None) -> dict:
    headers = {"content-type": "application/json"}
    if api_key:
        headers["authorization"] = f"Bearer {api_key}"
    request = urllib.request.Request(url, json.dumps(body).encode(), headers)
    with urllib.request.urlopen(request, timeout=30) as reply:
        return json.load(reply)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000")
    parser.add_argument("--task", default="box_stacking")
    parser.add_argument("--start", help="a PNG/JPEG file (default: a box-stacking state)")
    parser.add_argument("--goal", help="a PNG/JPEG file (default: a box-stacking state)")
    parser.add_argument("--out", type=Path, help="write each plan's images here")
    parser.add_argument("--api-key")
    args = parser.parse_args()

    body = {
        "task": args.task,
        "start": image(args.start) if args.start else START,
        "goal": image(args.goal) if args.goal else GOAL,
        "max_plans": 2,
    }
    reply = post(f"{args.url}/plan", body, args.api_key)
    if not reply["plans"]:
        raise SystemExit(f"no plan: {reply['reason']}")
    for k, plan in enumerate(reply["plans"]):
        print(f"plan {k}: {len(plan['actions'])} actions, support {plan['support']:.2f}")
        for step, action in enumerate(plan["actions"], 1):
            print(f"  {step}. {json.dumps(action)}")
        if args.out:  # the plan's images, start to goal
            args.out.mkdir(parents=True, exist_ok=True)
            for i, png in enumerate(plan["images"]):
                (args.out / f"plan{k}_{i}.png").write_bytes(base64.b64decode(png))


if __name__ == "__main__":
    main()

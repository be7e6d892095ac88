"""`lsr robot`: an example robot client."""

from __future__ import annotations

import argparse

from services.cli.common import env_settings, json_arg, robot_id_arg
from shared.appearance import LEVELS, levels_help
from shared.tasks import DEFAULT_TASK, get_task, task_names


def cmd_robot(args: argparse.Namespace) -> int:
    from services.robot import run_robot
    from shared.bus import close_quietly, open_session

    task = get_task(args.task)
    start = task.parse_state(json_arg(args.start_state))
    goal = task.parse_state(json_arg(args.goal_state))
    config = env_settings(zenoh_connect=args.connect).bus()
    config.open_timeout_s = 10.0
    session = open_session(config)
    try:
        episode = run_robot(
            session,
            args.robot_id,
            args.task,
            start,
            goal,
            args.max_steps,
            args.seed,
            report=args.report,
            appearance=args.appearance,
        )
    finally:
        close_quietly(session)
    outcome = "reached the goal" if episode.success else f"stopped: {episode.reason}"
    if episode.detail:  # the planner refused what the robot saw: say why, in its words
        outcome += f" ({episode.detail})"
    print(f"[{args.robot_id}] {outcome} after {len(episode.actions)} actions")
    return 0 if episode.success else 1


def register(sub: argparse._SubParsersAction) -> None:
    robot = sub.add_parser("robot", help="an example robot: plans over zenoh, acts in its sim")
    robot.add_argument("--robot-id", required=True, type=robot_id_arg)
    robot.add_argument("--task", default=DEFAULT_TASK, choices=task_names())
    robot.add_argument("--start-state", required=True, help="state JSON, inline or a file path")
    robot.add_argument("--goal-state", required=True, help="state JSON, inline or a file path")
    robot.add_argument("--max-steps", type=int, default=20)
    robot.add_argument("--seed", type=int, default=0)
    robot.add_argument(
        "--report",
        action="store_true",
        help="report every executed action as experience (the gateway records it where "
        "LSR_EXPERIENCE_DIR is set)",
    )
    robot.add_argument(
        "--appearance",
        choices=LEVELS,
        help="how its camera sees (default: the task's); at any level but clean it sends "
        f"whole camera frames, which the server registers to the table frame ({levels_help()})",
    )
    robot.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    robot.set_defaults(handler=cmd_robot)

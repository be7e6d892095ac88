"""Who may do what on the bus: zenoh configuration files for the router and every process.

The router authenticates every process by user name and password (zenoh's `usrpwd`) and applies
access-control rules, denying by default:
- each service (encoder, planner, apn, sim) may declare queryables, answer queries and hold a
  liveliness token only under its own keys (`lsr/{service}/**`, `lsr/alive/{service}/**`);
- the gateway and the sim may query the services and watch their tokens; the gateway alone
  serves `lsr/api/plan` and publishes on `lsr/robot/**`;
- a robot may query `lsr/api/plan` and the encoder's info keys (its image size), and subscribe
  to its own `lsr/robot/{robot_id}/plan` only;
- a monitor (`lsr ping` from outside, dashboards, tests) may watch tokens, ask every info key,
  query `lsr/api/plan` and subscribe to every robot's plans, and declare nothing.
A process without valid credentials cannot open a session at all. So a stranger can neither
serve `lsr/planner/...` (an impostor's plans would reach robots) nor ask anything.

    python -m shared.zenoh_access --out deploy/zenoh --robots arm-1 arm-2

writes `router.json5` (with the dictionary's path as the router will see it), `users.txt`
(user:password lines, random passwords) and one `{role}.json5` per process: give each process
its own as LSR_ZENOH_CONFIG (`lsr router` too, with `router.json5`). Every file but the
router's rules holds secrets and is written readable by its owner only.
"""

from __future__ import annotations

import argparse
import json
import re
import secrets
import sys
from pathlib import Path

SERVICE_ROLES = ("encoder", "planner", "apn", "sim")
BOTH = ["ingress", "egress"]
# A robot's user name embeds its id, and the dictionary is `user:password` lines.
ACL_ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def robot_user(robot_id: str) -> str:
    if not ACL_ROBOT_ID.match(robot_id):
        raise ValueError(
            f"robot id {robot_id!r}: with access control, ids are 1-64 of A-Z a-z 0-9 _ -"
        )
    return f"robot-{robot_id}"


def rule(rule_id: str, messages: list[str], keys: list[str], flows: list[str] = BOTH) -> dict:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": flows,
        "messages": messages,
        "key_exprs": keys,
    }


def access_control(robots: list[str]) -> dict:
    """The router's `access_control` section (deny by default)."""
    serve = ["declare_queryable", "query", "reply"]
    ask = ["query", "reply"]
    watch = ["declare_liveliness_subscriber", "liveliness_query"]
    rules = [
        rule("watch-tokens", watch, ["lsr/alive/**"]),
        rule("see-tokens", ["liveliness_token"], ["lsr/alive/**"], ["egress"]),
        rule("ask-services", ask, [f"lsr/{s}/**" for s in SERVICE_ROLES]),
        rule("ask-info", ask, [f"lsr/{s}/*/info/**" for s in SERVICE_ROLES]),
        rule("ask-encoder-info", ask, ["lsr/encoder/*/info/**"]),
        rule("ask-api", ask, ["lsr/api/plan"]),
        rule("serve-api", serve, ["lsr/api/plan"]),
        rule("publish-plans", ["put"], ["lsr/robot/**"], ["ingress"]),
        rule("read-all-plans", ["declare_subscriber", "put"], ["lsr/robot/**"]),
        rule("gateway-token", ["liveliness_token"], ["lsr/alive/gateway/**"], ["ingress"]),
    ]
    subjects = [{"id": role, "usernames": [role]} for role in (*SERVICE_ROLES, "gateway")]
    subjects.append({"id": "monitor", "usernames": ["monitor"]})
    policies = [
        {"rules": ["ask-services", "watch-tokens", "see-tokens"], "subjects": ["gateway", "sim"]},
        {"rules": ["serve-api", "publish-plans", "gateway-token"], "subjects": ["gateway"]},
        {
            "rules": ["ask-info", "ask-api", "read-all-plans", "watch-tokens", "see-tokens"],
            "subjects": ["monitor"],
        },
    ]
    for service in SERVICE_ROLES:
        rules.append(rule(f"serve-{service}", serve, [f"lsr/{service}/**"]))
        token = rule(f"token-{service}", ["liveliness_token"], [f"lsr/alive/{service}/**"])
        token["flows"] = ["ingress"]
        rules.append(token)
        policies.append({"rules": [f"serve-{service}", f"token-{service}"], "subjects": [service]})
    if robots:
        users = [robot_user(r) for r in robots]
        subjects.append({"id": "robots", "usernames": users})
        policies.append({"rules": ["ask-api", "ask-encoder-info"], "subjects": ["robots"]})
    for robot_id in robots:
        user = robot_user(robot_id)
        plans = rule(f"plans-{user}", ["declare_subscriber", "put"], [f"lsr/robot/{robot_id}/plan"])
        rules.append(plans)
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"rules": [plans["id"]], "subjects": [user]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def write_private(path: Path, text: str) -> None:
    path.touch(mode=0o600, exist_ok=True)
    path.chmod(0o600)
    path.write_text(text)


def write_deployment(out: Path, robots: list[str], dictionary_at: str | None = None) -> dict:
    """Write the router's and every role's configuration into `out`; returns {role: path}.

    `dictionary_at`: where the router will read `users.txt` (default: its path in `out`).
    """
    out.mkdir(parents=True, exist_ok=True)
    roles = [*SERVICE_ROLES, "gateway", "monitor", *(robot_user(r) for r in robots)]
    passwords = {role: secrets.token_urlsafe(24) for role in roles}
    write_private(out / "users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    dictionary = dictionary_at or str((out / "users.txt").resolve())
    router = {
        "transport": {"auth": {"usrpwd": {"dictionary_file": dictionary}}},
        "access_control": access_control(robots),
    }
    paths = {"router": out / "router.json5"}
    paths["router"].write_text(json.dumps(router, indent=2) + "\n")
    for role, password in passwords.items():
        client = {"transport": {"auth": {"usrpwd": {"user": role, "password": password}}}}
        paths[role] = out / f"{role}.json5"
        write_private(paths[role], json.dumps(client, indent=2) + "\n")
    return paths


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--robots", nargs="*", default=[], help="robot ids allowed on the bus")
    parser.add_argument("--dictionary-at", help="users.txt's path as the router sees it")
    args = parser.parse_args(argv)
    for role, path in write_deployment(args.out, args.robots, args.dictionary_at).items():
        print(f"{role}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

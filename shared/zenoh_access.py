"""Who may do what on the bus: zenoh configuration files for the router and every process.

The router authenticates every process by user name and password (zenoh's `usrpwd`) and applies
access-control rules, denying by default:
- each service (encoder, planner, apn, sim) may declare queryables, answer queries and hold a
  liveliness token only under its own keys (`lsr/{service}/**`, `lsr/alive/{service}/**`);
- the gateway and the sim may query the services and watch their tokens; the gateway alone
  serves `lsr/api/plan` and `lsr/experience/*` and publishes on `lsr/robot/**`;
- the sim publishes the steps of running episodes (`lsr/sim/*/progress/*`), which only the
  gateway may subscribe to;
- a robot may query `lsr/api/plan`, `lsr/experience/*` (what it did, for the roadmap to grow
  from) and the encoder's info keys (its image size), and subscribe
  to its own `lsr/robot/{robot_id}/plan` only;
- a monitor (`lsr ping` from outside, dashboards, tests) may watch tokens, ask every info key,
  query `lsr/api/plan` and subscribe to every robot's plans, and declare nothing;
- another router (user `router`) may carry everything under `lsr/**`: routers of several hosts
  mesh with `lsr router --connect` and apply these rules to their own processes.
A process without valid credentials cannot open a session at all. So a stranger can neither
serve `lsr/planner/...` (an impostor's plans would reach robots) nor ask anything.

    python -m shared.zenoh_access --out deploy/zenoh --robots arm-1 arm-2

writes `router.json5` (with the dictionary's path as the router will see it), `users.txt`
(user:password lines, random passwords) and one `{role}.json5` per process: give each process
its own as LSR_ZENOH_CONFIG (`lsr router` too, with `router.json5`: every router of a mesh takes
the same one). Every file but the certificates (`ca.pem`, `router.pem`) holds secrets and is
written readable by its owner only. A mesh under these rules needs TLS (`--tls-hosts`): a router
knows the routers it dials only by their certificate. The router's file (its password) and
`router.key` let their holder carry everything on `lsr/**`: keep them on router hosts only.
"""

from __future__ import annotations

import argparse
import json
import re
import secrets
import subprocess
import sys
from pathlib import Path

SERVICE_ROLES = ("encoder", "planner", "apn", "sim")
BOTH = ["ingress", "egress"]
PROGRESS_KEYS = "lsr/sim/*/progress/*"  # `shared.bus.progress_key`
EXPERIENCE_KEYS = "lsr/experience/*"  # `shared.bus.experience_key`: robots report, gateway records
ROUTER_USER = "router"  # what a router of a mesh presents to the routers it connects to
ROUTER_LEASE_MS = 2000
ROUTER_CN = "lsr-router"  # the common name of the routers' certificate (their names: its SANs)
MESH_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "declare_queryable",
    "query",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
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
        rule("serve-api", serve, ["lsr/api/plan", EXPERIENCE_KEYS]),
        rule("report-experience", ask, [EXPERIENCE_KEYS]),
        rule("publish-plans", ["put"], ["lsr/robot/**"], ["ingress"]),
        rule("read-all-plans", ["declare_subscriber", "put"], ["lsr/robot/**"]),
        rule("gateway-token", ["liveliness_token"], ["lsr/alive/gateway/**"], ["ingress"]),
        # Steps of running episodes: the sim publishes them, the gateway streams them on.
        rule("publish-progress", ["put"], [PROGRESS_KEYS], ["ingress"]),
        rule("read-progress", ["declare_subscriber", "put"], [PROGRESS_KEYS]),
        rule("mesh", MESH_MESSAGES, ["lsr/**"]),
    ]
    subjects = [{"id": role, "usernames": [role]} for role in (*SERVICE_ROLES, "gateway")]
    subjects.append({"id": "monitor", "usernames": ["monitor"]})
    # A router knows the routers that connect to it by their password, and the ones it connects
    # to by their certificate: usrpwd authenticates only the side that connects.
    subjects.append({"id": "routers", "usernames": [ROUTER_USER]})
    subjects.append({"id": "router-certificates", "cert_common_names": [ROUTER_CN]})
    policies = [
        {"rules": ["mesh"], "subjects": ["routers", "router-certificates"]},
        {"rules": ["ask-services", "watch-tokens", "see-tokens"], "subjects": ["gateway", "sim"]},
        {
            "rules": ["serve-api", "publish-plans", "gateway-token", "read-progress"],
            "subjects": ["gateway"],
        },
        {"rules": ["publish-progress"], "subjects": ["sim"]},
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
        policies.append(
            {"rules": ["ask-api", "ask-encoder-info", "report-experience"], "subjects": ["robots"]}
        )
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


def make_tls(out: Path, hosts: list[str]) -> None:
    """A private CA (ca.pem, ca.key) and the routers' certificate for `hosts` (names or IPs),
    made with the openssl command. Keep ca.key offline once the router's certificate exists."""
    names = [f"IP:{h}" if h.replace(".", "").isdigit() or ":" in h else f"DNS:{h}" for h in hosts]
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=out, check=True, capture_output=True)

    openssl(
        "req",
        "-x509",
        *ec,
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "3650",
        "-subj",
        "/CN=LSR zenoh CA",
    )
    openssl("req", *ec, "-keyout", "router.key", "-out", "router.csr", "-subj", f"/CN={ROUTER_CN}")
    (out / "router.ext").write_text(
        f"subjectAltName={','.join(names)}\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth\n"
    )
    openssl(
        "x509",
        "-req",
        "-in",
        "router.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        "router.pem",
        "-days",
        "825",
        "-extfile",
        "router.ext",
    )
    for name in ("ca.key", "router.key"):
        (out / name).chmod(0o600)
    for name in ("router.csr", "router.ext", "ca.srl"):
        (out / name).unlink(missing_ok=True)


def write_deployment(
    out: Path,
    robots: list[str],
    dictionary_at: str | None = None,
    tls_hosts: list[str] | None = None,
    files_at: str | None = None,
) -> dict:
    """Write the router's and every role's configuration into `out`; returns {role: path}.

    `dictionary_at`: where the router will read `users.txt` (default: its path in `out`).
    `tls_hosts`: the routers' host names or addresses (one certificate names every router of a
    mesh); then links are TLS (endpoints `tls/HOST:7447`): a CA and the routers' certificate are
    made, and every process, routers too, checks a router against `ca.pem`, read at `files_at`
    (default: `out`).
    """
    out.mkdir(parents=True, exist_ok=True)
    roles = [*SERVICE_ROLES, "gateway", "monitor", *(robot_user(r) for r in robots)]
    passwords = {role: secrets.token_urlsafe(24) for role in [ROUTER_USER, *roles]}
    write_private(out / "users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    dictionary = dictionary_at or str((out / "users.txt").resolve())
    folder = files_at or str(out.resolve())
    # A router checks its clients against the dictionary and presents its own credentials to
    # the routers it connects to (a mesh).
    usrpwd = {"user": ROUTER_USER, "password": passwords.pop(ROUTER_USER)}
    router: dict = {
        "transport": {
            "auth": {"usrpwd": {**usrpwd, "dictionary_file": dictionary}},
            # A link that goes silent (a router's or a client's) is given up after this, not
            # zenoh's 10 s, so that the mesh routes around a lost host while requests still
            # have time.
            "link": {"tx": {"lease": ROUTER_LEASE_MS, "keep_alive": 4}},
        },
        "access_control": access_control(robots),
    }
    client_link: dict = {}
    if tls_hosts:
        make_tls(out, tls_hosts)
        client_link = {"link": {"tls": {"root_ca_certificate": f"{folder}/ca.pem"}}}
        router["transport"]["link"]["tls"] = {
            "listen_private_key": f"{folder}/router.key",
            "listen_certificate": f"{folder}/router.pem",
            **client_link["link"]["tls"],  # to check the routers it connects to
        }
    paths = {"router": out / "router.json5"}
    write_private(paths["router"], json.dumps(router, indent=2) + "\n")
    for role, password in passwords.items():
        auth = {"usrpwd": {"user": role, "password": password}}
        client = {"transport": {"auth": auth, **client_link}}
        paths[role] = out / f"{role}.json5"
        write_private(paths[role], json.dumps(client, indent=2) + "\n")
    return paths


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--robots", nargs="*", default=[], help="robot ids allowed on the bus")
    parser.add_argument("--dictionary-at", help="users.txt's path as the router sees it")
    parser.add_argument(
        "--tls-hosts", nargs="*", default=[], help="the router's names/addresses: TLS links"
    )
    parser.add_argument("--files-at", help="this folder's path as the processes see it")
    args = parser.parse_args(argv)
    paths = write_deployment(
        args.out, args.robots, args.dictionary_at, args.tls_hosts, args.files_at
    )
    for role, path in paths.items():
        print(f"{role}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

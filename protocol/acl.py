"""The zenoh router's access control for the runs it serves, one run per identity.

zenoh's access control (the router's `access_control` config) has no templates: a rule names
literal key expressions, a subject literal certificate common names or user names. So the
rules are generated here, per run, from protocol.keys:

    identity            may, in run R only
    minority-rank.R     put chunks, events and stats; hold the rank liveliness token; get and
                        follow the spec
    minority-server.R   serve the spec (queryable) and put spec updates, frames, timing and
                        events; read everything of the run
    minority-viewer.R   read everything of the run, get the spec
    minority-oracle.R   read everything of the run, get the spec and put spec updates (the
                        oracle that follows the run: minority oracle follow)

and, for every run of the list at once, the role-wide identities `minority-server` and
`minority-viewer` (`shared`) and any session over the loopback interface (`loopback_readers`:
as a viewer). A rank's identity always names its run: a rank certificate of run A can put
nothing into run B, hold no token of B, and neither get nor follow B's spec. Everything else
is denied (default_permission "deny").

The identity is the client certificate's common name (mutual TLS; deploy/tls/make-run-certs.sh
issues them) and, with `usernames`, the same name as a user/password login.
`router_config_text` puts the result into a router config file (deploy/zenoh/router.json5);
`minority deploy acl` does both from the command line.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence

from minority.protocol import check, keys

RANK, SERVER, VIEWER, ORACLE = "rank", "server", "viewer", "oracle"
ROLES = (RANK, SERVER, VIEWER, ORACLE)
SHARED_DEFAULT = (SERVER, VIEWER)  # role-wide identities: the server and viewers of every run
LOOPBACK_INTERFACE = "lo"  # Linux; the subject "local" of deploy/zenoh/router.json5

# rule name -> (messages, flows, key expressions of run R)
_RULES = {
    "rank-put": (["put"], ["ingress"], lambda r: [keys.chunks(r), keys.event(r), keys.stats(r)]),
    "rank-token": (["liveliness_token"], ["ingress"], lambda r: [keys.rank_tokens(r)]),
    # fetch the spec (get) and follow its updates (subscribe to it)
    "spec-read": (["query", "declare_subscriber"], ["ingress"], lambda r: [keys.spec(r)]),
    "spec-read-out": (["reply", "put"], ["egress"], lambda r: [keys.spec(r)]),
    # learn who listens in the run (a publisher's matching status needs it)
    "see-readers": (["declare_subscriber", "declare_queryable"], ["egress"],
                    lambda r: [keys.everything(r)]),
    "server-put": (["put"], ["ingress"],
                   lambda r: [keys.spec(r), keys.frames(r), keys.timing(r), keys.event(r)]),
    "server-spec": (["declare_queryable", "reply"], ["ingress"], lambda r: [keys.spec(r)]),
    "oracle-put": (["put"], ["ingress"], lambda r: [keys.spec(r)]),  # spec updates
    "server-queries-in": (["query"], ["egress"], lambda r: [keys.spec(r)]),
    "read": (["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
             ["ingress"], lambda r: [keys.everything(r)]),
    "read-out": (["put", "liveliness_token"], ["egress"], lambda r: [keys.everything(r)]),
}
_ROLE_RULES = {
    RANK: ("rank-put", "rank-token", "spec-read", "spec-read-out", "see-readers"),
    SERVER: ("server-put", "server-spec", "server-queries-in", "read", "read-out", "spec-read",
             "spec-read-out", "see-readers"),
    VIEWER: ("read", "read-out", "spec-read", "spec-read-out", "see-readers"),
    ORACLE: ("oracle-put", "read", "read-out", "spec-read", "spec-read-out", "see-readers"),
}


def identity(role: str, run: str | None = None) -> str:
    """The certificate common name (and user name) of `role` in `run`, e.g.
    `minority-rank.column`; with no run the role-wide name, e.g. `minority-server`."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, not {role!r}")
    name = f"{keys.ROOT}-{role}"
    return name if run is None else f"{name}.{check.name(run, 'run')}"


def _checked_runs(runs: Iterable[str]) -> list[str]:
    if isinstance(runs, str):
        raise TypeError("runs is a list of run ids, not one string")
    out: list[str] = []
    for run in runs:
        check.name(run, "run")  # no "*": every rule names one run
        if run not in out:
            out.append(run)
    if not out:
        raise ValueError("no run: the access control is generated for at least one run id")
    return out


def router_access_control(runs: Sequence[str], *, shared: Iterable[str] = SHARED_DEFAULT,
                          loopback_readers: bool = True, usernames: bool = True) -> dict:
    """zenoh's `access_control` object (a dict for JSON) for a router serving `runs`.

    runs              the run ids (duplicates ignored); no key expression names another run
    shared            roles that also get a role-wide identity (`minority-server`,
                      `minority-viewer`) with the rights of that role in every run of `runs`;
                      () for per-run identities only. "rank" is refused: that is the hole a
                      per-run rank identity closes
    loopback_readers  sessions over the loopback interface (the router's tcp/127.0.0.1
                      listener, no certificate) read every run of `runs`, as a viewer
    usernames         user/password logins with the same names get the same rights
    """
    runs = _checked_runs(runs)
    if isinstance(shared, str):
        raise TypeError("shared is a list of roles, not one string")
    shared = list(dict.fromkeys(shared))
    for role in shared:
        if role not in (SERVER, VIEWER):
            raise ValueError(f"shared roles may be {SERVER!r} and {VIEWER!r}, not {role!r}: a "
                             "rank identity always names its run")
    rules, subjects, policies = [], [], []

    def subjects_of(name: str, subject_id: str) -> list[str]:
        subjects.append({"id": subject_id, "cert_common_names": [name]})
        if not usernames:
            return [subject_id]
        subjects.append({"id": f"{subject_id}-user", "usernames": [name]})
        return [subject_id, f"{subject_id}-user"]

    for run in runs:
        for name, (messages, flows, key_exprs) in _RULES.items():
            rules.append({"id": f"{name}.{run}", "messages": list(messages),
                          "flows": list(flows), "permission": "allow",
                          "key_exprs": key_exprs(run)})
        for role in ROLES:
            policies.append({"id": f"{role}.{run}",
                             "subjects": subjects_of(identity(role, run), f"{role}.{run}"),
                             "rules": [f"{name}.{run}" for name in _ROLE_RULES[role]]})
    every_run = {role: [f"{name}.{run}" for run in runs for name in _ROLE_RULES[role]]
                 for role in ROLES}
    for role in shared:
        policies.append({"id": role, "subjects": subjects_of(identity(role), role),
                         "rules": every_run[role]})
    if loopback_readers:
        subjects.append({"id": "local", "interfaces": [LOOPBACK_INTERFACE]})
        policies.append({"id": "local", "subjects": ["local"], "rules": every_run[VIEWER]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


# --- into a router config file -----------------------------------------------------------------
class ConfigTextError(ValueError):
    """A router config whose top-level object this module cannot find its way through."""


def _skip(text: str, i: int) -> int:
    """Past whitespace and JSON5 comments from i."""
    while i < len(text):
        if text[i].isspace():
            i += 1
        elif text.startswith("//", i):
            end = text.find("\n", i)
            i = len(text) if end < 0 else end + 1
        elif text.startswith("/*", i):
            end = text.find("*/", i + 2)
            if end < 0:
                raise ConfigTextError("unterminated /* comment")
            i = end + 2
        else:
            return i
    return i


def _string_end(text: str, i: int) -> int:
    """Past the JSON5 string that starts at i (quote ' or ")."""
    quote, i = text[i], i + 1
    while i < len(text):
        if text[i] == "\\":
            i += 2
        elif text[i] == quote:
            return i + 1
        else:
            i += 1
    raise ConfigTextError("unterminated string")


def _value_end(text: str, i: int) -> int:
    """Past the JSON5 value that starts at i."""
    if text[i] in "'\"":
        return _string_end(text, i)
    if text[i] not in "{[":
        while i < len(text) and text[i] not in ",}]" and not text[i].isspace():
            i += 1
        return i
    depth = 0
    while i < len(text):
        i = _skip(text, i)
        if i >= len(text):
            break
        c = text[i]
        if c in "'\"":
            i = _string_end(text, i)
            continue
        if c in "{[":
            depth += 1
        elif c in "}]":
            depth -= 1
            if depth == 0:
                return i + 1
        i += 1
    raise ConfigTextError("unbalanced brackets")


def _top_level_members(text: str):
    """(key, key_start, value_start, value_end) of each member of the top-level object, and
    the index of its closing brace."""
    i = _skip(text, 0)
    if i >= len(text) or text[i] != "{":
        raise ConfigTextError("the config is not a JSON5 object")
    members, i = [], _skip(text, i + 1)
    while i < len(text) and text[i] != "}":
        start = i
        if text[i] in "'\"":
            i = _string_end(text, i)
            key = json.loads('"' + text[start + 1:i - 1] + '"')
        else:
            while i < len(text) and (text[i].isalnum() or text[i] in "_$"):
                i += 1
            key = text[start:i]
            if not key:
                raise ConfigTextError(f"expected a key at offset {start}")
        i = _skip(text, i)
        if i >= len(text) or text[i] != ":":
            raise ConfigTextError(f"expected ':' after {key!r}")
        value_start = _skip(text, i + 1)
        if value_start >= len(text):
            raise ConfigTextError(f"no value for {key!r}")
        value_end = _value_end(text, value_start)
        members.append((key, start, value_start, value_end))
        i = _skip(text, value_end)
        if i < len(text) and text[i] == ",":
            i = _skip(text, i + 1)
    if i >= len(text):
        raise ConfigTextError("the top-level object is not closed")
    return members, i


def router_config_text(base: str, access_control: dict, note: str = "") -> str:
    """The router config `base` (JSON5 text, e.g. deploy/zenoh/router.json5) with its
    top-level `access_control` replaced by (or, without one, given) `access_control`;
    comments and every other setting are kept. `note` becomes a comment line on top."""
    members, close = _top_level_members(base)
    rendered = json.dumps(access_control, indent=2).replace("\n", "\n  ")
    existing = [m for m in members if m[0] == "access_control"]
    if existing:
        _, _, start, end = existing[0]
        text = base[:start] + rendered + base[end:]
    else:
        before = base[:close].rstrip()
        comma = "" if before.endswith((",", "{")) else ","
        text = f"{before}{comma}\n  access_control: {rendered},\n{base[close:]}"
    if note:
        text = "".join(f"// {line}\n" for line in note.splitlines()) + text
    return text

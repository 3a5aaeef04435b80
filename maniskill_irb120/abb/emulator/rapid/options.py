"""RobotWare options and the RAPID names they provide: what a controller without the option refuses at load time.
An IRC5 resolves every name of a module when it loads it, whatever branch would run; :func:`check_options` walks a
whole parse tree (names the task declares itself are its own and never gated). Names are case-insensitive.
See docs/rapid_subset.md, "Loading a task".
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from lark import Token, Tree


@dataclass(frozen=True)
class RobotWareOption:
    """One RobotWare option: its id (``"616-1"``), its name and the RAPID names it brings."""

    id: str
    name: str
    types: frozenset[str]
    routines: frozenset[str]
    data: frozenset[str]

    def names(self) -> frozenset[str]:
        return self.types | self.routines | self.data

    def __str__(self) -> str:
        return f"{self.id} {self.name}"


def _names(text: str) -> frozenset[str]:
    return frozenset(text.split())


# Sources (the ABB manuals were not at hand, see docs/reference.md "IRC5 / RAPID behaviour an emulator must reproduce"):
# * socket API -> 616-1 PC Interface or 672-1 Socket Messaging: open_abb issue 6 ("Missing option ... SocketCreate
#   requires the option PC Interface"); ros-industrial/abb issue 147 ("Reference to unknown function
#   SocketGetStatus", answered "you need 672-1 or 616-1"). The routine and type names are those of ABB's socket
#   API as open_abb and abb_driver (ROS_socket.sys) use it; the SOCKET_* status constants and the ERR_SOCK_* names
#   beyond TIMEOUT/CLOSED/ADDR_INUSE are integrator knowledge (verify).
# * world zones -> 608-1 World Zones (verify): WZBoxDef, WZLimSup, wztemporary, wzstationary, shapedata per
#   docs/reference.md; the other WZ* routines are integrator knowledge (verify).
# * EGM -> 689-1 Externally Guided Motion (docs/reference.md; names as abb_libegm's RAPID examples use them; verify).
# * multitasking -> 623-1 Multitasking (docs/reference.md: abb_driver's state server needs it; names verify).
_SOCKET_TYPES = _names("socketdev socketstatus")
_SOCKET_ROUTINES = _names(
    "SocketCreate SocketBind SocketListen SocketAccept SocketConnect SocketReceive SocketSend SocketClose "
    "SocketGetStatus SocketReceiveFrom SocketSendTo SocketPeek"  # SocketPeek: RobotWare 6 (verify)
)
_SOCKET_DATA = _names(
    "ERR_SOCK_TIMEOUT ERR_SOCK_CLOSED ERR_SOCK_ADDR_INUSE "
    # integrator knowledge (verify):
    "ERR_SOCK_NET_UNREACH ERR_SOCK_ADDR_INVALID ERR_SOCK_UNEXPECTED "
    "SOCKET_CREATED SOCKET_CONNECTED SOCKET_BOUND SOCKET_LISTENING SOCKET_CLOSED"
)

OPTIONS: dict[str, RobotWareOption] = {
    o.id: o
    for o in (
        RobotWareOption("616-1", "PC Interface", _SOCKET_TYPES, _SOCKET_ROUTINES, _SOCKET_DATA),
        RobotWareOption("672-1", "Socket Messaging", _SOCKET_TYPES, _SOCKET_ROUTINES, _SOCKET_DATA),
        RobotWareOption(
            "608-1",
            "World Zones",
            _names("wztemporary wzstationary shapedata"),
            _names(
                "WZBoxDef WZCylDef WZSphDef WZHomeJointDef WZLimJointDef WZLimSup WZDOSet WZEnable WZDisable WZFree"
            ),
            frozenset(),
        ),
        RobotWareOption(
            "689-1",
            "Externally Guided Motion",
            _names("egmident egmstate egmstopmode egmframetype egm_minmax"),
            _names(
                "EGMGetId EGMReset EGMGetState EGMSetupUC EGMSetupAI EGMSetupAO EGMSetupGI EGMActJoint EGMActPose "
                "EGMRunJoint EGMRunPose EGMStop EGMStreamStart EGMStreamStop"
            ),
            _names("EGM_STOP_HOLD EGM_STOP_RAMP_DOWN EGM_FRAME_BASE EGM_FRAME_TOOL EGM_FRAME_WOBJ EGM_FRAME_WORLD"),
        ),
        RobotWareOption("623-1", "Multitasking", _names("syncident taskid tasks"), _names("WaitSyncTask"), frozenset()),
    )
}


def _index() -> dict[str, tuple[RobotWareOption, ...]]:
    index: dict[str, list[RobotWareOption]] = {}
    for option in OPTIONS.values():
        for name in option.names():
            index.setdefault(name.lower(), []).append(option)
    return {k: tuple(v) for k, v in index.items()}


GATED: dict[str, tuple[RobotWareOption, ...]] = _index()  # lower-case name -> the options that provide it


def providers(name: str) -> tuple[RobotWareOption, ...]:
    """The options that provide RAPID name ``name`` (empty: every controller has it)."""
    return GATED.get(name.lower(), ())


def parse_options(spec: Iterable[str] | str | None) -> tuple[str, ...]:
    """Installed option ids from ``"616-1,608-1"`` or an iterable; an unknown id is refused by name."""
    if spec is None:
        return ()
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    ids = tuple(dict.fromkeys(s.strip() for s in items if s.strip()))
    unknown = [i for i in ids if i not in OPTIONS]
    if unknown:
        known = ", ".join(str(o) for o in OPTIONS.values())
        raise ValueError(f"unknown RobotWare option(s) {', '.join(unknown)}; known: {known}")
    return ids


# ---- the walk over a parse tree ---------------------------------------------------------------------------------
_DECLARING = {  # rule -> index of the child NAME it declares
    "data_decl": 3,
    "proc": 1,
    "func": 2,
    "trap": 1,
    "record_decl": 0,
    "req_param": 2,
    "param_alt": 2,
    "for_stmt": 0,
}


def declared_names(tree: Tree) -> set[str]:
    """Every name the modules of ``tree`` declare (routines, data, records, parameters, FOR variables)."""
    out: set[str] = set()
    for t in tree.iter_subtrees():
        i = _DECLARING.get(t.data)
        if i is not None and isinstance(t.children[i], Token):
            out.add(t.children[i].lower())
        elif t.data == "record_field":
            out.add(t.children[1].lower())
    return out


def name_uses(t: Tree) -> Iterable[Token]:
    """The NAME tokens of ``t`` that refer to something: types, routines, data (not module names, record
    component names or the names of optional arguments)."""
    skip: set[int] = set()
    if t.data in ("module", "field", "opt_arg"):
        skip = {0}
    elif t.data == "record_field":
        skip = {1}
    elif t.data in ("module_attrs", "cond_arg"):
        return
    for i, c in enumerate(t.children):
        if isinstance(c, Tree):
            yield from name_uses(c)
        elif isinstance(c, Token) and c.type == "NAME" and i not in skip:
            yield c


def missing_options(module: Tree, installed: Iterable[str], own: set[str]) -> list[tuple[Token, tuple]]:
    """(token, providers) for each use in ``module`` of a name whose option is not ``installed``; ``own``: names
    the task declares itself (never gated)."""
    have = set(installed)
    out = []
    for tok in name_uses(module):
        low = tok.lower()
        opts = GATED.get(low)
        if opts and low not in own and not any(o.id in have for o in opts):
            out.append((tok, opts))
    return out

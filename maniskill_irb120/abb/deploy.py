"""Deploying the RAPID server to an IRC5 over Robot Web Services 1.0 (RobotWare 6), the way integrators' tools do
it, with ``abb-robot-client`` (the ``real`` extra) as the client: ``maniskill-irb120 deploy --controller URL``.

The steps, each refusing before anything changes where the controller says no:

1. read the RobotWare version, the installed options, the operating mode, the controller state and whether the
   program runs (a running program is never touched: stop it first);
2. pick the files the option matrix allows (docs/real_robot.md, section 1): the serial build needs no option, the
   TCP build 616-1 PC Interface or 672-1 Socket Messaging, the controller-side world zone 608-1 World Zones; a
   build asked for that the options do not allow is refused with the option's name;
3. upload them to ``$HOME/IRB120/`` (the file service);
4. take mastership (RWS requires it to load modules and move the program pointer) and load the modules into
   ``T_ROB1``; on a load error read the event log and print the controller's own messages, and unload what this
   run loaded;
5. only after the operator confirms (``--yes`` for scripts), set the program pointer to the entry routine
   ``IRB120Server``; the program stays stopped.

``deploy start`` starts the program remotely in AUTO only, and only when the loaded server's ``ALLOW_AUTO`` is
TRUE (docs/real_robot.md, section 3): the server moves the robot in manual reduced speed unless an integrator
changed that constant deliberately; in the manual modes the operator starts it on the FlexPendant with the
enabling device held. ``deploy status``, ``deploy stop`` and ``deploy unload`` (our modules and files out, the
program pointer back to main) complete it.

abb-robot-client (0.4) has no calls for the system's options, mastership, the file service's folders, loading
modules or the program pointer: :class:`Controller` adds them over its own request path (its session, digest
authentication and error parsing), with the resources RWS 1.0 documents (docs/real_robot.md has the table).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

SOCKET_OPTIONS = ("616-1", "672-1")
ZONE_OPTION = "608-1"
OPTION_NAMES = {"616-1": "PC Interface", "672-1": "Socket Messaging", "608-1": "World Zones"}
CORE_FILE = "IRB120Server.mod"
CHANNEL_FILES = {"serial": "IRB120Serial.mod", "tcp": "IRB120Socket.mod"}
ZONE_FILE = "IRB120Zone.sys"
OUR_MODULES = ("IRB120Server", "IRB120Serial", "IRB120Socket", "IRB120Zone")
ENTRY = "IRB120Server"  # the server's entry routine
TASK = "T_ROB1"
FOLDER = "IRB120"  # under $HOME
DEFAULT_USER = "Default User"  # RWS's documented default user and password (abb-robot-client's defaults)
DEFAULT_PASSWORD = "robotics"
# the constants an integrator sets in the files before loading them (docs/real_robot.md, section 2)
SHOWN_CONSTANTS = ("SER_CHANNEL", "SOCK_ADDRESS", "SOCK_PORT", "PC_ADDRESS", "ALLOW_AUTO", "SPEED_PERCENT")


class DeployRefused(Exception):
    """The deployment stopped: the message says why and what was left as it was."""


def option_label(opt: str) -> str:
    return f"{opt} {OPTION_NAMES[opt]}" if opt in OPTION_NAMES else opt


@dataclass
class Plan:
    """The files to load, in order, and why each was picked."""

    channel: str
    zone: bool
    files: list[str]
    reasons: list[str] = field(default_factory=list)


def choose_files(options: list[str] | tuple[str, ...], channel: str = "auto", zone: str = "auto") -> Plan:
    """The files the option matrix allows for a controller with ``options`` (ids, ``"616-1"``). ``channel``:
    ``auto`` (TCP when a socket option is installed, else serial), ``serial`` or ``tcp``; ``zone``: ``auto`` (the
    world zone when 608-1 is installed), ``on`` or ``off``. Raises :class:`DeployRefused` naming the missing
    option when what was asked for does not fit."""
    if channel not in ("auto", "serial", "tcp"):
        raise ValueError(f"channel={channel!r}: use auto, serial or tcp")
    if zone not in ("auto", "on", "off"):
        raise ValueError(f"zone={zone!r}: use auto, on or off")
    have = set(options)
    sockets = [o for o in SOCKET_OPTIONS if o in have]
    reasons = []
    if channel == "tcp" and not sockets:
        raise DeployRefused(
            "the TCP build needs RobotWare option 616-1 PC Interface or 672-1 Socket Messaging; this controller has "
            "neither (use --channel serial, which needs no option)"
        )
    if channel == "auto":
        channel = "tcp" if sockets else "serial"
        reasons.append(
            f"{CHANNEL_FILES['tcp']}: the TCP build, as {option_label(sockets[0])} provides the socket API"
            if sockets
            else f"{CHANNEL_FILES['serial']}: the serial build, which needs no option (no 616-1 or 672-1 installed)"
        )
    elif channel == "tcp":
        reasons.append(f"{CHANNEL_FILES['tcp']}: the TCP build, as asked ({option_label(sockets[0])} installed)")
    else:
        reasons.append(f"{CHANNEL_FILES['serial']}: the serial build, as asked (needs no option)")
    if zone == "on" and ZONE_OPTION not in have:
        raise DeployRefused(
            f"the world zone {ZONE_FILE} needs RobotWare option {option_label(ZONE_OPTION)}, which this controller "
            "does not have (use --zone off or auto)"
        )
    with_zone = ZONE_OPTION in have if zone == "auto" else zone == "on"
    if with_zone:
        reasons.append(f"{ZONE_FILE}: the controller-side world zone ({option_label(ZONE_OPTION)} installed)")
    else:
        why = "as asked" if zone == "off" else f"no {option_label(ZONE_OPTION)}"
        reasons.append(f"no {ZONE_FILE}: {why}; the PC's envelope still checks every step")
    files = [CORE_FILE, CHANNEL_FILES[channel]] + ([ZONE_FILE] if with_zone else [])
    return Plan(channel, with_zone, files, [f"{CORE_FILE}: the server core (every build)"] + reasons)


def shipped_rapid_dir() -> Path:
    """The RAPID files this package ships (assets/rapid)."""
    return Path(str(resources.files("maniskill_irb120.assets").joinpath("rapid")))


def constants_of(text: str) -> dict[str, str]:
    """The module constants an integrator sets (:data:`SHOWN_CONSTANTS`) as the file declares them."""
    out = {}
    for m in re.finditer(r"^\s*(?:LOCAL\s+)?CONST\s+\w+\s+(\w+)\s*:=\s*([^;]+);", text, re.M | re.I):
        if m.group(1).upper() in SHOWN_CONSTANTS:
            out[m.group(1).upper()] = m.group(2).strip()
    return out


def _rws_base():
    try:
        from abb_robot_client.rws import RWS
    except ImportError as e:  # the optional extra
        raise DeployRefused(
            "deploy needs abb-robot-client (pip install 'maniskill-irb120[real]', or bash scripts/setup.sh real)"
        ) from e
    return RWS


def connect(url: str, user: str = DEFAULT_USER, password: str = DEFAULT_PASSWORD):
    """A :class:`Controller` client for ``url`` (``http://HOST[:PORT]``)."""
    if not re.fullmatch(r"http://[^/\s]+", url.rstrip("/")):
        raise DeployRefused(
            f"--controller {url!r}: use http://HOST (RWS 1.0, RobotWare 6); RobotWare 7 / OmniCore serves RWS 2.0 "
            "over https, which this command does not speak (docs/real_robot.md)"
        )
    RWS = _rws_base()

    class Controller(RWS):
        """abb-robot-client's RWS 1.0 client plus the calls a deployment needs that it lacks, each over its own
        request path (``_do_get``/``_do_post``: its session, digest auth and error parsing)."""

        def system(self) -> tuple[dict, list[str]]:
            """(the ``sys-system-li`` item, the option strings) of ``/rw/system`` (abb_librws reads the same)."""
            items = self._do_get("rw/system")["_embedded"]["_state"]
            sysinfo = next((i for i in items if i.get("_type") == "sys-system-li"), {})
            return sysinfo, [i["option"] for i in items if i.get("_type") == "sys-option-li"]

        def request_mastership(self) -> None:
            self._do_post("rw/mastership?action=request")

        def release_mastership(self) -> None:
            self._do_post("rw/mastership?action=release")

        def make_folder(self, parent: str, name: str) -> None:
            self._do_post(f"fileservice/{parent}", {"fs-action": "create", "fs-newname": name})

        def load_module(self, path: str, replace: bool = True) -> None:
            self._do_post(
                f"rw/rapid/tasks/{TASK}?action=loadmod", {"modulepath": path, "replace": str(replace).lower()}
            )

        def unload_module(self, name: str) -> None:
            self._do_post(f"rw/rapid/tasks/{TASK}?action=unloadmod", {"module": name})

        def modules(self) -> list[str]:
            return [i["name"] for i in self._do_get(f"rw/rapid/tasks/{TASK}/modules")["_embedded"]["_state"]]

        def set_pp_routine(self, routine: str, module: str) -> None:
            self._do_post(
                f"rw/rapid/tasks/{TASK}/pcp?action=set-pp-routine",
                {"routine": routine, "module": module, "userlevel": "false"},
            )

        def pcp(self) -> tuple[str, str]:
            item = self._do_get(f"rw/rapid/tasks/{TASK}/pcp")["_embedded"]["_state"][0]
            return item.get("modulename", ""), item.get("routinename", "")

    return Controller(url.rstrip("/"), user, password)


@dataclass
class ControllerInfo:
    name: str
    robotware: str
    options: list[str]  # ids, "616-1"
    option_texts: list[str]
    opmode: str  # AUTO, MANR, MANF
    ctrlstate: str
    execstate: str  # running, stopped
    speedratio: float


def read_info(c) -> ControllerInfo:
    """What the controller is and what it is doing (step 1)."""
    try:
        sysinfo, texts = c.system()
    except Exception as e:
        raise DeployRefused(_explain(e, "reading /rw/system")) from None
    ids = [m.group(1) for t in texts if (m := re.match(r"\s*(\d{3}-\d)\b", t))]
    return ControllerInfo(
        name=sysinfo.get("name", "?"),
        robotware=sysinfo.get("rwversionname") or sysinfo.get("rwversion", "?"),
        options=ids,
        option_texts=texts,
        opmode=c.get_operation_mode(),
        ctrlstate=c.get_controller_state(),
        execstate=c.get_execution_state().ctrlexecstate,
        speedratio=c.get_speedratio(),
    )


def _explain(e: Exception, what: str) -> str:
    text = str(e)
    if "401" in text:
        return f"{what}: the controller refused the user name or password (HTTP 401): check --user/--password"
    return f"{what}: {text}"


def _say_info(info: ControllerInfo, say: Callable[[str], None]) -> None:
    say(f"controller: {info.name}, RobotWare {info.robotware}")
    say(f"options: {', '.join(info.option_texts) or 'none'}")
    say(f"operating mode {info.opmode}, controller state {info.ctrlstate}, program {info.execstate}")


def _last_seq(c) -> int:
    return max((e.seqnum for e in c.read_event_log()), default=0)


def _code(event) -> str:
    """The event number after a space, or nothing where the controller gave none (0)."""
    return f" {event.code}" if event.code else ""


def _new_events(c, after: int) -> list:
    return sorted((e for e in c.read_event_log() if e.seqnum > after), key=lambda e: e.seqnum)


def deploy(
    c,
    say: Callable[[str], None],
    confirm: Callable[[str], bool],
    channel: str = "auto",
    zone: str = "auto",
    rapid_dir: Path | None = None,
    folder: str = FOLDER,
) -> None:
    """Steps 1-5 of the module docstring; raises :class:`DeployRefused` saying why it stopped and what was left."""
    info = read_info(c)
    _say_info(info, say)
    if not info.robotware.startswith("6."):
        raise DeployRefused(
            f"RobotWare {info.robotware}: this command speaks RWS 1.0 (RobotWare 6); nothing was changed"
        )
    if info.execstate != "stopped":
        raise DeployRefused(
            f"the program is {info.execstate}: stop it first (maniskill-irb120 deploy stop); nothing was changed"
        )
    plan = choose_files(info.options, channel, zone)
    say(f"picked the {plan.channel} build{' with the world zone' if plan.zone else ''}:")
    for r in plan.reasons:
        say(f"  {r}")
    src = Path(rapid_dir) if rapid_dir else shipped_rapid_dir()
    texts = {}
    for f in plan.files:
        p = src / f
        if not p.is_file():
            raise DeployRefused(f"{p}: no such file (--rapid-dir holds the edited copies of the shipped files)")
        texts[f] = p.read_bytes()
        consts = constants_of(texts[f].decode("utf-8", "replace"))
        if consts:
            say(f"  {f} sets " + ", ".join(f"{k} = {v}" for k, v in consts.items()))
    remote = f"$HOME/{folder}"
    try:
        if folder not in c.list_files("$HOME"):
            c.make_folder("$HOME", folder)
        for f, data in texts.items():
            c.upload_file(f"{remote}/{f}", data)
        listed = set(c.list_files(remote))
    except Exception as e:
        raise DeployRefused(_explain(e, f"uploading to {remote}")) from None
    missing = [f for f in plan.files if f not in listed]
    if missing:
        raise DeployRefused(f"uploaded but not listed in {remote}: {', '.join(missing)}")
    say(f"uploaded {', '.join(plan.files)} to {remote}")
    try:
        c.request_mastership()
    except Exception as e:
        raise DeployRefused(_explain(e, "requesting mastership") + f"; the files stay in {remote}") from None
    loaded: list[str] = []
    try:
        present = [m for m in c.modules() if m in OUR_MODULES]
        for m in present:  # an earlier deployment: out first, so that exactly the picked files are loaded
            c.unload_module(m)
        if present:
            say(f"unloaded the earlier deployment's {', '.join(present)}")
        seq = _last_seq(c)
        for f in plan.files:
            try:
                c.load_module(f"{remote}/{f}", replace=True)
            except Exception as e:
                lines = [f"loading {remote}/{f} into {TASK} failed: {e}"]
                lines += [f"  controller event{_code(ev)}: {ev.title}: {ev.desc}" for ev in _new_events(c, seq)]
                for m in reversed(loaded):
                    c.unload_module(m)
                lines.append(
                    f"unloaded what this run loaded ({', '.join(loaded) or 'nothing'}); the files stay in {remote}"
                )
                raise DeployRefused("\n".join(lines)) from None
            loaded.append(Path(f).stem)
        say(f"loaded {', '.join(loaded)} into {TASK}")
        if not confirm(f"Set the program pointer to {ENTRY} in {TASK} (the program stays stopped)?"):
            say(f"program pointer not set: the modules are loaded; set PP to {ENTRY} on the FlexPendant")
            return
        c.set_pp_routine(ENTRY, ENTRY)
        module, routine = c.pcp()
        if routine != ENTRY:
            raise DeployRefused(f"the program pointer stands at {module}/{routine}, not at {ENTRY}")
        say(f"program pointer at {module}/{routine}; the program is stopped")
    finally:
        try:
            c.release_mastership()
        except Exception:  # a lost connection releases it too
            pass
    say(
        "once per controller, on the FlexPendant (system parameters, which deploy leaves alone): "
        f"{ENTRY}Restart as the RESTART event routine"
        + (
            f"; {ZONE_FILE} as an automatically loaded system module with IRB120ZonePowerOn as its POWER ON event"
            " routine (loaded over RWS it is gone after a restart)"
            if plan.zone
            else ""
        )
    )
    if info.opmode == "AUTO":
        say("the controller is in AUTO: the server refuses motion there unless ALLOW_AUTO (deploy start checks it)")
    else:
        say(f"next: in {info.opmode}, hold the enabling device and press Start on the FlexPendant")


def status(c, say: Callable[[str], None], events: int = 5) -> None:
    info = read_info(c)
    _say_info(info, say)
    say(f"speed ratio {info.speedratio:g} %")
    ours = [m for m in c.modules() if m in OUR_MODULES]
    say(f"our modules in {TASK}: {', '.join(ours) or 'none'}")
    module, routine = c.pcp()
    say(f"program pointer: {module + '/' + routine if routine else 'none'}")
    log = sorted(c.read_event_log(), key=lambda e: e.seqnum)[-events:]
    say(f"last {len(log)} events:")
    for e in log:
        say(f"  {e.tstamp:%H:%M:%S}{_code(e)} {e.title}: {e.desc}")


def stop(c, say: Callable[[str], None]) -> None:
    c.stop()
    state = c.get_execution_state().ctrlexecstate
    if state != "stopped":
        raise DeployRefused(f"the program is still {state} after stop")
    say("program stopped")


def start(c, say: Callable[[str], None], confirm: Callable[[str], bool]) -> None:
    """Start the server remotely: in AUTO only, and only with ALLOW_AUTO TRUE in the loaded core."""
    info = read_info(c)
    _say_info(info, say)
    if info.execstate == "running":
        say("the program already runs")
        return
    if info.opmode != "AUTO":
        raise DeployRefused(
            f"the controller is in {info.opmode}: a program is started remotely in AUTO only; in manual reduced speed"
            " the operator holds the enabling device and presses Start on the FlexPendant"
        )
    try:
        allow = c.get_rapid_variable(f"{ENTRY}/ALLOW_AUTO")
    except Exception as e:
        raise DeployRefused(_explain(e, "reading ALLOW_AUTO (is the server deployed?)")) from None
    if allow.strip().upper() != "TRUE":
        raise DeployRefused(
            "refused to start in AUTO: ALLOW_AUTO is FALSE in the loaded IRB120Server.mod, so the server moves the "
            "robot only in manual reduced speed (docs/real_robot.md, section 3); switch to manual reduced speed, or "
            "set ALLOW_AUTO := TRUE deliberately after the cell's risk assessment and deploy again"
        )
    if not confirm("Start the program in AUTO (ALLOW_AUTO is TRUE; the robot moves on the PC's commands)?"):
        say("not started")
        return
    if info.ctrlstate != "motoron":
        c.set_controller_state("motoron")
    c.start(cycle="asis")
    say(f"program {c.get_execution_state().ctrlexecstate}")


def unload(c, say: Callable[[str], None], folder: str = FOLDER) -> None:
    """Our modules out of T_ROB1 and our files out of $HOME, the program pointer back to main."""
    info = read_info(c)
    if info.execstate != "stopped":
        raise DeployRefused(f"the program is {info.execstate}: stop it first; nothing was changed")
    c.request_mastership()
    try:
        ours = [m for m in c.modules() if m in OUR_MODULES]
        for m in ours:
            c.unload_module(m)
        say(f"unloaded {', '.join(ours) or 'nothing (none of ours was loaded)'}")
        c.resetpp()
        module, routine = c.pcp()
        say(f"program pointer at {module}/{routine} (the task's main entry)")
    finally:
        try:
            c.release_mastership()
        except Exception:
            pass
    remote = f"$HOME/{folder}"
    if folder in c.list_files("$HOME"):
        names = c.list_files(remote)
        for n in names:
            c.delete_file(f"{remote}/{n}")
        c.delete_file(remote)
        if folder in c.list_files("$HOME"):  # abb-robot-client's delete_file does not check the answer
            raise DeployRefused(f"{remote} could not be removed (is something else in it?)")
        say(f"removed {remote} ({', '.join(names) or 'empty'})")
    else:
        say(f"no {remote} to remove")

"""Deploying the RAPID server to an IRC5 (RobotWare 6) over Robot Web Services 1.0 as a transaction that never
leaves the cell worse than it found it: access first, a new folder per deploy, load, read back, switch over, and on
any failure or Ctrl-C the previous deployment put back. The steps and what each rolls back: docs/real_robot.md,
"The deploy transaction". abb-robot-client (the ``real`` extra) is the client; :class:`Controller` adds the
resources it lacks."""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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
FOLDER = "IRB120"  # under $HOME: one subfolder per deployment and the manifest
MANIFEST = "deploy.json"  # what deploy wrote on the controller: the only files it ever removes
MANIFEST_FORMAT = 1
DEFAULT_USER = "Default User"  # RWS's documented default user and password (abb-robot-client's defaults)
DEFAULT_PASSWORD = "robotics"
# the constants an integrator sets in the files before loading them (docs/real_robot.md, section 2)
SHOWN_CONSTANTS = ("SER_CHANNEL", "SOCK_ADDRESS", "SOCK_PORT", "PC_ADDRESS", "ALLOW_AUTO", "SPEED_PERCENT")
MANUAL_MODES = ("MANR", "MANF")
RMMP_WAIT_S = 60.0  # how long the operator has to grant remote access (RMMP) on the FlexPendant
MASTERSHIP_WAIT_S = 60.0  # how long to wait for mastership another client holds (a vanished one's session ends)
POLL_S = 0.25


class DeployRefused(Exception):
    """The deployment stopped: the message says why and what the controller holds now."""


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


def same_value(declared: str, read: str) -> bool:
    """Whether a constant read back over RWS (RAPID's text form) is the value the file declares: strings exactly,
    booleans by name, numbers by value (the controller prints ``5000`` or ``5000.0`` as it likes)."""
    a, b = declared.strip(), read.strip()
    if a.startswith('"') or b.startswith('"'):  # RWS quotes a string's value or not (verify): both are read
        return _unquoted(a) == _unquoted(b)
    if a.upper() in ("TRUE", "FALSE") or b.upper() in ("TRUE", "FALSE"):
        return a.upper() == b.upper()
    try:
        return abs(float(a) - float(b)) <= 1e-6 * max(1.0, abs(float(a)))
    except ValueError:
        return re.sub(r"\s+", "", a) == re.sub(r"\s+", "", b)


def _unquoted(text: str) -> str:
    return text[1:-1] if len(text) >= 2 and text[0] == text[-1] == '"' else text


def _state(doc) -> list | None:
    """An RWS 1.0 JSON answer's ``_embedded._state`` list, or None where the answer has none."""
    if not isinstance(doc, dict):
        return None
    items = (doc.get("_embedded") or {}).get("_state")
    return items if isinstance(items, list) else None


def option_texts(system: dict | None, options: dict | None = None) -> list[str] | None:
    """The option texts (``"616-1 PC Interface"``) in any shape RobotWare 6 is documented or captured to give:
    flat ``sys-option-li`` items in ``/rw/system`` (abb_librws reads these), a ``sys-options-li`` item holding its
    own list (RobotWare 6.05, captured in a public RWS mock), or the items of ``/rw/system/options``. None where
    no answer holds a recognisable option list, so that nothing is read as "no options"."""
    found: list[str] | None = None
    for doc, whole_list in ((system, False), (options, True)):
        items = _state(doc)
        if items is None:
            continue
        texts = []
        recognised = whole_list and all(isinstance(i, dict) and "option" in i for i in items)
        for item in items:
            if not isinstance(item, dict):
                continue
            kind = str(item.get("_type", ""))
            if kind in ("sys-option-li", "sys-option") and isinstance(item.get("option"), str):
                texts.append(item["option"])
                recognised = True
            elif kind in ("sys-options-li", "sys-options"):
                inner = item.get("options")
                if inner is None:
                    inner = _state(item)
                if isinstance(inner, list):
                    texts += [i["option"] for i in inner if isinstance(i, dict) and isinstance(i.get("option"), str)]
                    recognised = True
        if recognised:
            found = (found or []) + [t for t in texts if t not in (found or [])]
    return found


def option_ids(texts: list[str]) -> list[str]:
    """The option numbers (``"616-1"``) at the start of option texts."""
    return [m.group(1) for t in texts if (m := re.match(r"\s*(\d{3}-\d+)\b", t))]


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
        request path (``_do_get``/``_do_post``: its session, digest authentication and error parsing)."""

        def system_answers(self) -> tuple[dict, dict | None]:
            """The raw answers of ``/rw/system`` and, where that lists no options, ``/rw/system/options``."""
            system = self._do_get("rw/system")
            if option_texts(system) is not None:
                return system, None
            try:
                return system, self._do_get("rw/system/options")
            except Exception:  # not served: the raw /rw/system answer goes into the refusal
                return system, None

        def request_mastership(self) -> None:
            self._do_post("rw/mastership?action=request")

        def release_mastership(self) -> None:
            self._do_post("rw/mastership?action=release")

        def ask_rmmp(self, privilege: str = "modify") -> None:
            """Ask the operator for remote access (RMMP); abb-robot-client's ``request_rmmp`` waits only 5 s."""
            self._do_post("users/rmmp", {"privilege": privilege})

        def rmmp_status(self) -> str:
            """``PENDING``, ``GRANTED`` or ``REJECTED``; each poll keeps a pending request alive."""
            return str(self._do_get("users/rmmp/poll")["_embedded"]["_state"][0].get("status", "")).upper()

        def cancel_rmmp(self) -> None:
            self._do_post("users/rmmp?action=cancel")

        def make_folder(self, parent: str, name: str) -> None:
            self._do_post(f"fileservice/{parent}", {"fs-action": "create", "fs-newname": name})

        def remove(self, path: str) -> None:
            """Delete a file or an empty folder; raises where the controller refuses (abb-robot-client's
            ``delete_file`` does not look at the answer)."""
            res = self._session.delete("/".join([self.base_url, "fileservice", path]), auth=self.auth)
            try:
                if not res.ok:
                    raise RuntimeError(f"deleting {path}: HTTP {res.status_code} {res.reason}")
            finally:
                res.close()

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


def _raw(doc, limit: int = 600) -> str:
    text = json.dumps(doc, separators=(",", ":")) if doc is not None else "no answer"
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} characters)"


def read_info(c) -> ControllerInfo:
    """What the controller is and what it is doing (step 1); refuses, with the raw answer, an option list in a
    shape it does not know."""
    try:
        system, options = c.system_answers()
    except Exception as e:
        raise DeployRefused(_explain(e, "reading /rw/system")) from None
    texts = option_texts(system, options)
    if texts is None:
        raise DeployRefused(
            "could not find the installed options in the controller's answer (no sys-option-li items in /rw/system "
            f"or /rw/system/options), so the build cannot be chosen; nothing was changed. /rw/system: {_raw(system)}"
            f"; /rw/system/options: {_raw(options)}"
        )
    sysinfo = next((i for i in _state(system) or [] if i.get("_type") == "sys-system-li"), {})
    return ControllerInfo(
        name=sysinfo.get("name", "?"),
        robotware=sysinfo.get("rwversionname") or sysinfo.get("rwversion", "?"),
        options=option_ids(texts),
        option_texts=texts,
        opmode=c.get_operation_mode(),
        ctrlstate=c.get_controller_state(),
        execstate=c.get_execution_state().ctrlexecstate,
        speedratio=c.get_speedratio(),
    )


def _explain(e: BaseException, what: str) -> str:
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


# ================================================================================================ access
@contextmanager
def access(
    c,
    opmode: str,
    say: Callable[[str], None],
    rmmp_wait_s: float = RMMP_WAIT_S,
    mastership_wait_s: float = MASTERSHIP_WAIT_S,
) -> Iterator[None]:
    """Write access before anything is written: in the manual modes the operator's grant of remote access (RMMP)
    on the FlexPendant first (ABB's RWS reference: "In manual mode, mastership can be gained after getting RMMP"),
    then mastership, waiting up to ``mastership_wait_s`` while another client holds it (a client that vanished
    loses it when its session ends). Both are given back on leaving, however it is left."""
    if opmode not in ("AUTO", *MANUAL_MODES):
        raise DeployRefused(f"the operating mode is {opmode}: deploy works in AUTO, MANR or MANF; nothing was changed")
    rmmp = opmode in MANUAL_MODES
    if rmmp:
        _get_rmmp(c, say, rmmp_wait_s)
    try:
        _get_mastership(c, say, mastership_wait_s)
        try:
            yield
        finally:
            try:
                c.release_mastership()
            except Exception:  # a lost connection ends the session, which releases it too
                pass
    finally:
        if rmmp:
            try:
                c.cancel_rmmp()
            except Exception:
                pass


def _get_rmmp(c, say: Callable[[str], None], wait_s: float) -> None:
    try:
        c.ask_rmmp("modify")
    except Exception as e:
        raise DeployRefused(_explain(e, "requesting remote access (RMMP)") + "; nothing was changed") from None
    say(f"manual mode: waiting up to {wait_s:g} s for the operator to grant remote access on the FlexPendant")
    deadline = time.monotonic() + wait_s
    while True:
        try:
            status = c.rmmp_status()
        except Exception as e:
            raise DeployRefused(_explain(e, "polling remote access (RMMP)") + "; nothing was changed") from None
        if status == "GRANTED":
            say("remote access granted on the FlexPendant")
            return
        if status != "PENDING" or time.monotonic() > deadline:
            try:
                c.cancel_rmmp()
            except Exception:
                pass
            why = f"the request was {status.lower()}" if status != "PENDING" else f"no answer within {wait_s:g} s"
            raise DeployRefused(
                f"the operator did not grant remote access on the FlexPendant ({why}); in the manual modes a "
                "controller gives mastership to a remote client only with that grant; nothing was changed"
            )
        time.sleep(POLL_S)


def _get_mastership(c, say: Callable[[str], None], wait_s: float) -> None:
    deadline = time.monotonic() + wait_s
    told = False
    while True:
        try:
            c.request_mastership()
            return
        except Exception as e:
            if time.monotonic() > deadline:
                raise DeployRefused(
                    _explain(e, "requesting mastership")
                    + f" (waited {wait_s:g} s; another client, an HMI or RobotStudio, holds it: release it there, or "
                    "wait until a vanished client's session ends); nothing was changed"
                ) from None
            if not told:
                say(f"mastership refused ({e}): waiting up to {wait_s:g} s for it to be released")
                told = True
        time.sleep(POLL_S * 2)


# ================================================================================================ manifest
def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _home_has(c, path: str, name: str) -> bool:
    """Whether folder ``path`` (one that exists) lists ``name``; a failed listing raises, never reads as "absent",
    which would start a fresh manifest and forget the deployments the old one records."""
    return name in c.list_files(path)


def read_manifest(c, folder: str = FOLDER) -> dict | None:
    """The manifest of what deploy wrote on the controller, or None where there is none."""
    if not _home_has(c, "$HOME", folder) or not _home_has(c, f"$HOME/{folder}", MANIFEST):
        return None
    raw = c.read_file(f"$HOME/{folder}/{MANIFEST}")
    try:
        m = json.loads(raw)
        if not isinstance(m, dict) or m.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"format {m.get('format') if isinstance(m, dict) else '?'}, not {MANIFEST_FORMAT}")
    except ValueError as e:
        raise DeployRefused(
            f"$HOME/{folder}/{MANIFEST} is not a manifest this deploy can read ({e}); nothing was changed: move it "
            "aside on the FlexPendant and deploy again"
        ) from None
    m.setdefault("deployments", {})
    return m


def _write_manifest(c, folder: str, m: dict) -> None:
    if not _home_has(c, "$HOME", folder):
        c.make_folder("$HOME", folder)
    c.upload_file(f"$HOME/{folder}/{MANIFEST}", json.dumps(m, indent=1).encode())


def _new_manifest() -> dict:
    return {"format": MANIFEST_FORMAT, "written_by": "maniskill-irb120 deploy", "active": None, "deployments": {}}


def _remove_deployment(c, folder: str, entry: dict) -> list[str]:
    """Remove the files a deployment wrote (only those) and its folder when nothing else is in it; returns what
    stayed."""
    remote = f"$HOME/{entry['folder']}"
    if not _home_has(c, f"$HOME/{folder}", entry["folder"].split("/")[-1]):
        return []
    present = set(c.list_files(remote))
    for name in entry["files"]:
        if name in present:
            c.remove(f"{remote}/{name}")
    left = sorted(present - set(entry["files"]))
    if not left:
        c.remove(remote)
    return [f"{remote}/{n}" for n in left]


@dataclass
class Holdings:
    """What of ours the task holds: our modules, in load order, and the program pointer."""

    modules: list[str]
    pp: tuple[str, str] | None


def holdings(c) -> Holdings:
    module, routine = c.pcp()
    return Holdings([m for m in c.modules() if m in OUR_MODULES], (module, routine) if routine else None)


def describe(c, folder: str = FOLDER) -> str:
    """One line on what the controller holds now, read from it (never from what was intended)."""
    try:
        h = holdings(c)
        m = read_manifest(c, folder)
    except Exception as e:  # the controller no longer answers: say so rather than guess
        return f"the controller did not answer when asked what it holds ({e}); check on the FlexPendant"
    pp = f"PP at {h.pp[0]}/{h.pp[1]}" if h.pp else "no program pointer (set it on the FlexPendant)"
    if not h.modules:
        return f"the controller holds none of our modules; {pp}"
    active = (m or {}).get("active")
    entry = (m or {}).get("deployments", {}).get(active or "")
    source = f" (deployment {active}, files in $HOME/{entry['folder']})" if entry else ""
    return f"the controller holds {', '.join(h.modules)}{source}; {pp}"


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Ctrl-C is held off while a rollback runs, so a second one cannot leave the task half-restored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, lambda *_: None)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def rollback(c, m: dict, folder: str = FOLDER) -> list[str]:
    """Put back what an unfinished deployment (``m["pending"]``) found: our modules as they were, from the files
    they were loaded from, and the program pointer; then its own files out. Returns what was done, step by step;
    a step that fails is said and the rest still run."""
    pending = m["pending"]
    before = pending["previous"]
    done: list[str] = []

    def step(what: str, fn: Callable[[], object]) -> bool:
        try:
            fn()
            return True
        except Exception as e:
            done.append(f"could not {what}: {e}")
            return False

    loaded = []
    step("list the task's modules", lambda: loaded.extend(m for m in c.modules() if m in OUR_MODULES))
    for mod in reversed(loaded):
        step(f"unload {mod}", lambda mod=mod: c.unload_module(mod))
    if loaded:
        done.append(f"unloaded {', '.join(loaded)}")
    reloaded = [Path(p).stem for p in before["files"] if step(f"reload {p}", lambda p=p: c.load_module(p))]
    if reloaded:
        done.append(f"reloaded {', '.join(reloaded)} from {Path(before['files'][0]).parent}")
    unknown = [x for x in before["modules"] if x not in [Path(p).stem for p in before["files"]]]
    if unknown:
        done.append(f"could not reload {', '.join(unknown)}: deploy has no record of their files")
    if before["pp"]:
        module, routine = before["pp"]
        if step(f"set the program pointer to {module}/{routine}", lambda: c.set_pp_routine(routine, module)):
            done.append(f"program pointer back at {module}/{routine} (at the routine's start)")
    new = m["deployments"].get(pending["id"])
    if new is not None:
        left: list[str] = []
        if step(f"remove $HOME/{new['folder']}", lambda: left.extend(_remove_deployment(c, folder, new))):
            m["deployments"].pop(pending["id"])
            done.append(f"removed this deployment's $HOME/{new['folder']}" + (f" (left: {left})" if left else ""))
    m["pending"] = None
    if m["deployments"]:
        step(f"update $HOME/{folder}/{MANIFEST}", lambda: _write_manifest(c, folder, m))
    else:  # nothing of deploy's left on the controller: neither is its manifest, nor the folder if it is empty
        step(f"remove $HOME/{folder}/{MANIFEST}", lambda: _drop_manifest(c, folder))
    return done


def _drop_manifest(c, folder: str) -> None:
    c.remove(f"$HOME/{folder}/{MANIFEST}")
    if not c.list_files(f"$HOME/{folder}"):
        c.remove(f"$HOME/{folder}")


def recover(c, say: Callable[[str], None], folder: str = FOLDER) -> dict:
    """The manifest, after rolling back a deployment that was interrupted (killed) before it switched over."""
    m = read_manifest(c, folder) or _new_manifest()
    if m.get("pending"):
        say(f"an earlier deploy ({m['pending']['id']}) was interrupted before it finished: rolling it back")
        with _sigint_deferred():
            for line in rollback(c, m, folder):
                say(f"  {line}")
        say(f"  {describe(c, folder)}")
    return m


def _previous_files(c, m: dict, folder: str, ours: list[str]) -> list[str]:
    """The files our loaded modules came from: the active deployment's, or an earlier version's files directly
    in $HOME/IRB120 (never overwritten since)."""
    entry = m["deployments"].get(m.get("active") or "")
    if entry and [Path(f).stem for f in entry["files"]] == ours:
        return [f"$HOME/{entry['folder']}/{f}" for f in entry["files"]]
    listed = set(c.list_files(f"$HOME/{folder}")) if _home_has(c, "$HOME", folder) else set()
    out = []
    for mod in ours:
        name = next((n for n in (f"{mod}.mod", f"{mod}.sys") if n in listed), None)
        if name:
            out.append(f"$HOME/{folder}/{name}")
    return out


# ================================================================================================ deploy
def deploy(
    c,
    say: Callable[[str], None],
    confirm: Callable[[str], bool],
    channel: str = "auto",
    zone: str = "auto",
    rapid_dir: Path | None = None,
    folder: str = FOLDER,
    rmmp_wait_s: float = RMMP_WAIT_S,
    mastership_wait_s: float = MASTERSHIP_WAIT_S,
) -> str:
    """The deploy transaction (docs/real_robot.md, "The deploy transaction"); returns the new deployment's id.
    Raises :class:`DeployRefused` saying why it stopped, what was rolled back and what the controller holds."""
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
    texts: dict[str, bytes] = {}
    consts: dict[str, dict[str, str]] = {}
    for f in plan.files:
        p = src / f
        if not p.is_file():
            raise DeployRefused(f"{p}: no such file (--rapid-dir holds the edited copies of the shipped files)")
        texts[f] = p.read_bytes()
        consts[f] = constants_of(texts[f].decode("utf-8", "replace"))
        if consts[f]:
            say(f"  {f} sets " + ", ".join(f"{k} = {v}" for k, v in consts[f].items()))
    with access(c, info.opmode, say, rmmp_wait_s, mastership_wait_s):
        m = recover(c, say, folder)
        return _transaction(c, say, confirm, m, plan, texts, consts, folder, info.opmode)


def _transaction(c, say, confirm, m: dict, plan: Plan, texts: dict, consts: dict, folder: str, opmode: str) -> str:
    before = holdings(c)
    dep_id = time.strftime("%Y%m%d-%H%M%S") + "-" + secrets.token_hex(2)
    remote = f"$HOME/{folder}/{dep_id}"
    m["deployments"][dep_id] = {
        "folder": f"{folder}/{dep_id}",
        "files": {f: _sha(data) for f, data in texts.items()},
        "constants": {Path(f).stem: v for f, v in consts.items() if v},
    }
    m["pending"] = {
        "id": dep_id,
        "previous": {
            "active": m.get("active"),
            "modules": before.modules,
            "files": _previous_files(c, m, folder, before.modules),
            "pp": list(before.pp) if before.pp else None,
        },
    }
    _write_manifest(c, folder, m)  # from here on an interruption, even a killed process, is rolled back
    try:
        c.make_folder(f"$HOME/{folder}", dep_id)
        for f, data in texts.items():
            c.upload_file(f"{remote}/{f}", data)
        for f, data in texts.items():  # what the controller stores is what was read from disk here
            got = c.read_file(f"{remote}/{f}")
            if got != data:
                raise DeployRefused(f"{remote}/{f} reads back {len(got)} bytes that differ from the {len(data)} sent")
        say(f"uploaded {', '.join(plan.files)} to {remote} (read back, sha256 equal)")
        for mod in reversed(before.modules):  # the earlier deployment out, so that exactly the picked files load
            c.unload_module(mod)
        if before.modules:
            say(f"unloaded the earlier deployment's {', '.join(before.modules)}")
        seq = _last_seq(c)
        loaded: list[str] = []
        for f in plan.files:
            try:
                c.load_module(f"{remote}/{f}", replace=True)
            except Exception as e:
                lines = [f"loading {remote}/{f} into {TASK} failed: {e}"]
                lines += [f"  controller event{_code(ev)}: {ev.title}: {ev.desc}" for ev in _new_events(c, seq)]
                raise DeployRefused("\n".join(lines)) from None
            loaded.append(Path(f).stem)
        _verify(c, plan, consts)
        say(f"loaded {', '.join(loaded)} into {TASK}; read back: the modules and " + _shown(consts))
        if confirm(f"Set the program pointer to {ENTRY} in {TASK} (the program stays stopped)?"):
            c.set_pp_routine(ENTRY, ENTRY)
            module, routine = c.pcp()
            if routine != ENTRY:
                raise DeployRefused(f"the program pointer stands at {module}/{routine}, not at {ENTRY}")
            say(f"program pointer at {module}/{routine}; the program is stopped")
        else:
            say(f"program pointer not set: the modules are loaded; set PP to {ENTRY} on the FlexPendant")
    except (Exception, KeyboardInterrupt) as e:
        why = "interrupted (Ctrl-C)" if isinstance(e, KeyboardInterrupt) else str(e) or type(e).__name__
        if not isinstance(e, (DeployRefused, KeyboardInterrupt)):
            why = _explain(e, "the controller")
        with _sigint_deferred():
            done = rollback(c, m, folder)
            now = describe(c, folder)
        raise DeployRefused(
            "\n".join([why, "rolled back to what this deploy found:", *(f"  {d}" for d in done), now])
        ) from None
    previous = m.get("active")
    m["active"], m["pending"] = dep_id, None
    _write_manifest(c, folder, m)  # the switch-over: from here this deployment is the one to keep
    say(f"deployment {dep_id} is active: {describe(c, folder)}")
    for old in [k for k in m["deployments"] if k != dep_id]:
        try:
            left = _remove_deployment(c, folder, m["deployments"][old])
            m["deployments"].pop(old)
            say(
                f"removed the superseded deployment's files ({old})"
                + (f"; left what it did not write: {left}" if left else "")
            )
        except Exception as e:
            say(f"could not remove the superseded deployment {old}'s files ({e}); the next deploy tries again")
    _write_manifest(c, folder, m)
    if previous is None and before.modules:
        say(f"the modules loaded before ({', '.join(before.modules)}) were not deploy's: their files were left alone")
    _after(plan, say, opmode)
    return dep_id


def _shown(consts: dict) -> str:
    pairs = [f"{k} = {v}" for per_file in consts.values() for k, v in per_file.items()]
    return ", ".join(pairs) if pairs else "no settings to compare"


def _verify(c, plan: Plan, consts: dict) -> None:
    """What is loaded is what was uploaded: exactly our picked modules, and every shown setting as the file says."""
    want = [Path(f).stem for f in plan.files]
    ours = [x for x in c.modules() if x in OUR_MODULES]
    if sorted(ours) != sorted(want):
        raise DeployRefused(f"after loading, {TASK} holds {', '.join(ours) or 'none'} of ours, not {', '.join(want)}")
    for f, per_file in consts.items():
        for name, value in per_file.items():
            got = c.get_rapid_variable(f"{Path(f).stem}/{name}")
            if not same_value(value, got):
                raise DeployRefused(
                    f"{Path(f).stem}/{name} reads back as {got} from the controller, but the uploaded file sets "
                    f"{value}: what is loaded is not what this deploy uploaded"
                )


def _after(plan: Plan, say: Callable[[str], None], opmode: str) -> None:
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
    if opmode == "AUTO":
        say("the controller is in AUTO: the server refuses motion there unless ALLOW_AUTO (deploy start checks it)")
    else:
        say(f"next: in {opmode}, hold the enabling device and press Start on the FlexPendant")


# ================================================================================================ the rest
def status(c, say: Callable[[str], None], events: int = 5, folder: str = FOLDER) -> None:
    info = read_info(c)
    _say_info(info, say)
    say(f"speed ratio {info.speedratio:g} %")
    h = holdings(c)
    say(f"our modules in {TASK}: {', '.join(h.modules) or 'none'}")
    say(f"program pointer: {h.pp[0] + '/' + h.pp[1] if h.pp else 'none'}")
    m = read_manifest(c, folder)
    if m and m.get("active") in m["deployments"]:
        say(f"active deployment: {m['active']} ($HOME/{m['deployments'][m['active']]['folder']})")
    if m and m.get("pending"):
        say(f"an interrupted deploy ({m['pending']['id']}) is pending: the next deploy or unload rolls it back")
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


def unload(
    c,
    say: Callable[[str], None],
    folder: str = FOLDER,
    rmmp_wait_s: float = RMMP_WAIT_S,
    mastership_wait_s: float = MASTERSHIP_WAIT_S,
) -> None:
    """Our modules out of T_ROB1 and the files the manifest lists out of $HOME, nothing else: the program pointer
    moves (to main) only where one of our modules held it."""
    info = read_info(c)
    if info.execstate != "stopped":
        raise DeployRefused(f"the program is {info.execstate}: stop it first; nothing was changed")
    with access(c, info.opmode, say, rmmp_wait_s, mastership_wait_s):
        m = recover(c, say, folder)
        before = holdings(c)
        for mod in reversed(before.modules):
            c.unload_module(mod)
        say(f"unloaded {', '.join(before.modules) or 'nothing (none of ours was loaded)'}")
        after = holdings(c)
        if before.pp and before.pp[0] in OUR_MODULES:
            c.resetpp()
            module, routine = c.pcp()
            say(f"program pointer at {module}/{routine} (the task's main entry; it stood in our {before.pp[0]})")
        elif before.pp and after.pp != before.pp:
            c.set_pp_routine(before.pp[1], before.pp[0])
            say(f"program pointer back at {before.pp[0]}/{before.pp[1]}, where it stood")
        elif before.pp:
            say(f"program pointer left at {before.pp[0]}/{before.pp[1]}")
        else:
            say("no program pointer before, none set")
        _unload_files(c, say, folder, m)


def _unload_files(c, say: Callable[[str], None], folder: str, m: dict) -> None:
    remote = f"$HOME/{folder}"
    if not _home_has(c, "$HOME", folder):
        say(f"no {remote} to remove")
        return
    if not m["deployments"] and not _home_has(c, remote, MANIFEST):
        say(f"no {MANIFEST} in {remote}: no files of deploy's are known there; {remote} left as it is")
        return
    removed, kept = [], []
    for entry in m["deployments"].values():
        kept += _remove_deployment(c, folder, entry)
        removed += [f"{entry['folder'].split('/')[-1]}/{f}" for f in entry["files"]]
    c.remove(f"{remote}/{MANIFEST}")
    others = c.list_files(remote)
    if others:
        say(
            f"removed {', '.join(removed) or 'no deployment files'} and {MANIFEST} from {remote}; left what deploy "
            f"did not write: {', '.join(sorted(others))}"
        )
    else:
        c.remove(remote)
        say(f"removed {remote} ({', '.join(removed + [MANIFEST])})")

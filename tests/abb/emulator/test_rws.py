"""Robot Web Services 1.0 on the emulator (``abb/emulator/rws.py``), through abb-robot-client's own calls where it
has them: every answer parses; digest authentication refuses a wrong password, a wrong user and a replayed
request; an unknown resource gets RWS's error body; loading, unloading and moving the program pointer need
mastership; the option matrix of docs/real_robot.md is enforced on modules loaded over RWS, the controller's
message going to the event log; remote start needs AUTO and the motors on."""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
import time

import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
rws_client = pytest.importorskip("abb_robot_client.rws")
requests = pytest.importorskip("requests")

from maniskill_irb120.abb.emulator.controller import rapid_file  # noqa: E402
from maniskill_irb120.abb.emulator.rws import CODE_NO_MASTERSHIP, REALM  # noqa: E402

ABBException, RWS = rws_client.ABBException, rws_client.RWS


def upload(r, *files: str, text: dict[str, str] | None = None) -> None:
    """The shipped files (or ``text``'s versions) into $HOME/IRB120."""
    if "IRB120" not in r.list_files("$HOME"):
        r._do_post("fileservice/$HOME", {"fs-action": "create", "fs-newname": "IRB120"})
    for f in files:
        data = (text or {}).get(f) or rapid_file(f).read_text()
        r.upload_file(f"$HOME/IRB120/{f}", data.encode())


def load(r, f: str) -> None:
    r._do_post("rw/rapid/tasks/T_ROB1?action=loadmod", {"modulepath": f"$HOME/IRB120/{f}", "replace": "true"})


def master(r) -> None:
    """Mastership in a manual mode: RMMP first, granted by the emulated operator, then the request (RWS 1.0
    reference: "In manual mode, mastership can be gained after getting RMMP")."""
    r._do_post("users/rmmp", {"privilege": "modify"})
    for _ in range(40):
        status = r._do_get("users/rmmp/poll")["_embedded"]["_state"][0]["status"]
        if status != "PENDING":
            break
        time.sleep(0.05)
    assert status == "GRANTED", status
    r._do_post("rw/mastership?action=request")


def modules(r) -> list[str]:
    return [m["name"] for m in r._do_get("rw/rapid/tasks/T_ROB1/modules")["_embedded"]["_state"]]


def test_abb_robot_client_parses_every_answer(rws_emulator):
    emu = rws_emulator(options="616-1,608-1", op_mode="auto")
    r = RWS(emu.url)
    assert r.get_execution_state().ctrlexecstate == "stopped"
    assert r.get_controller_state() == "motoroff"
    assert r.get_operation_mode() == "AUTO"
    r.set_speedratio(50)
    assert r.get_speedratio() == 50.0
    tasks = r.get_tasks()
    assert tasks["T_ROB1"].motiontask and tasks["T_ROB1"].active
    upload(r, "IRB120Server.mod", "IRB120Socket.mod", "IRB120Zone.sys")
    assert r.list_files("$HOME/IRB120") == ["IRB120Server.mod", "IRB120Socket.mod", "IRB120Zone.sys"]
    assert r.read_file("$HOME/IRB120/IRB120Zone.sys") == rapid_file("IRB120Zone.sys").read_bytes()
    system = r._do_get("rw/system")["_embedded"]["_state"]
    assert [s["option"] for s in system if s["_type"] == "sys-option-li"] == ["616-1 PC Interface", "608-1 World Zones"]
    assert system[0]["rwversionname"].startswith("6.")
    r._do_post("rw/mastership?action=request")
    for f in ("IRB120Server.mod", "IRB120Socket.mod", "IRB120Zone.sys"):
        load(r, f)
    assert modules(r) == ["MainModule", "IRB120Server", "IRB120Socket", "IRB120Zone"]
    assert r.get_rapid_variable("IRB120Server/ALLOW_AUTO") == "FALSE"
    assert r.get_rapid_variable("IRB120Socket/SOCK_PORT") == "5000"
    pers = r.get_rapid_variables()
    assert [(p["symburl"], p["dattyp"]) for p in pers] == [("RAPID/T_ROB1/IRB120Server/tGripper", "tooldata")]
    # a PERS changes over RWS (in AUTO without mastership, as abb-robot-client's set_rapid_variable assumes); a
    # CONST does not
    r._do_post("rw/mastership?action=release")
    r.set_rapid_variable("IRB120Server/tGripper", _gripper_with_mass(r.get_rapid_variable("IRB120Server/tGripper")))
    assert "0.7" in r.get_rapid_variable("IRB120Server/tGripper")
    with pytest.raises(ABBException, match="is a CONST"):
        r.set_rapid_variable("IRB120Server/ALLOW_AUTO", "TRUE")
    assert r.get_rapid_variable("IRB120Server/ALLOW_AUTO") == "FALSE"
    r._do_post("rw/mastership?action=request")
    r.resetpp()  # the task's main entry: the stock main
    assert r._do_get("rw/rapid/tasks/T_ROB1/pcp")["_embedded"]["_state"][0]["routinename"] == "main"
    r.set_controller_state("motoron")
    assert r.get_controller_state() == "motoron"
    r.start()
    assert r.get_execution_state().ctrlexecstate in ("running", "stopped")  # the stock main returns at once
    r.stop()
    log = r.read_event_log()
    assert [e.seqnum for e in log] == sorted((e.seqnum for e in log), reverse=True)  # newest first
    assert any(e.title == "Module loaded" and "IRB120Zone" in e.desc for e in log)
    r.close()


def _gripper_with_mass(text: str) -> str:
    """tooldata [robhold,[tframe],[mass,...]] with the mass 0.7 kg instead of 0.6 kg."""
    assert ",[0.6," in text, text
    return text.replace(",[0.6,", ",[0.7,")


def test_wrong_credentials_get_401_and_no_session(rws_emulator):
    emu = rws_emulator()
    for user, password in (("Default User", "wrong"), ("Someone", "robotics")):
        with pytest.raises(ABBException, match="401") as e:
            RWS(emu.url, user, password).get_execution_state()
        assert e.value.code == -401
    raw = requests.get(f"{emu.url}/rw/panel/opmode?json=1", auth=requests.auth.HTTPDigestAuth("x", "y"))
    assert raw.status_code == 401 and "Set-Cookie" not in raw.headers
    challenge = raw.headers["WWW-Authenticate"]
    assert challenge.startswith("Digest ") and f'realm="{REALM}"' in challenge and 'qop="auth"' in challenge
    assert requests.get(f"{emu.url}/rw/panel/opmode?json=1").status_code == 401  # no credentials at all
    assert requests.get(f"{emu.url}/rw/panel/opmode?json=1", cookies={"ABBCX": "guessed"}).status_code == 401


def test_a_replayed_digest_answer_is_refused(rws_emulator):
    """RFC 7616: the nonce count of a nonce must grow; the same Authorization header sent twice is a replay."""
    emu = rws_emulator()
    uri = "/rw/panel/opmode?json=1"
    nonce = re.search(r'nonce="([^"]+)"', requests.get(emu.url + uri).headers["WWW-Authenticate"]).group(1)
    md5 = lambda s: hashlib.md5(s.encode()).hexdigest()  # noqa: E731
    ha1, ha2 = md5(f"Default User:{REALM}:robotics"), md5(f"GET:{uri}")
    response = md5(f"{ha1}:{nonce}:00000001:abcd:auth:{ha2}")
    header = (
        f'Digest username="Default User", realm="{REALM}", nonce="{nonce}", uri="{uri}", response="{response}", '
        'qop=auth, nc=00000001, cnonce="abcd", algorithm=MD5'
    )
    first = requests.get(emu.url + uri, headers={"Authorization": header})
    assert first.status_code == 200 and first.json()["_embedded"]["_state"][0]["opmode"] == "MANR"
    assert requests.get(emu.url + uri, headers={"Authorization": header}).status_code == 401
    wrong = header.replace(response, md5("something else"))
    assert (
        requests.get(emu.url + uri, headers={"Authorization": wrong.replace("00000001", "00000002")}).status_code == 401
    )


def test_an_unknown_resource_gets_rws_s_error_body(rws_emulator):
    emu = rws_emulator()
    r = RWS(emu.url)
    with pytest.raises(ABBException, match="no such resource") as e:
        r._do_get("rw/rapid/nothing")
    assert e.value.code == -404
    raw = r._session.get(f"{emu.url}/rw/rapid/nothing?json=1", auth=r.auth)
    assert raw.status_code == 404 and raw.headers["Content-Type"] == "application/json"
    assert set(raw.json()["_embedded"]["status"]) == {"code", "msg"}
    with pytest.raises(ABBException, match="unknown file system location"):
        r.list_files("$TEMP")
    master(r)
    with pytest.raises(ABBException, match=r"'\.\.' and '\.' are not allowed"):
        r._do_post("rw/rapid/tasks/T_ROB1?action=loadmod", {"modulepath": "$HOME/../etc/x.mod"})
    with pytest.raises(Exception, match="Not Found"):  # PUT into a folder nobody created (the client says no more)
        r.upload_file("$HOME/nowhere/x.mod", b"MODULE X\nENDMODULE\n")
    raw = r._session.put(f"{emu.url}/fileservice/$HOME/nowhere/x.mod", b"MODULE X\nENDMODULE\n", auth=r.auth)
    assert raw.status_code == 404 and "folder nowhere does not exist" in raw.json()["_embedded"]["status"]["msg"]
    assert r.get_operation_mode() == "MANR"  # the controller serves on after each refusal


def test_loading_needs_mastership_and_a_refusal_changes_nothing(rws_emulator):
    emu = rws_emulator()
    a, b = RWS(emu.url), RWS(emu.url)
    upload(a, "IRB120Server.mod")
    with pytest.raises(ABBException, match="needs mastership") as e:
        load(a, "IRB120Server.mod")
    assert e.value.code == CODE_NO_MASTERSHIP  # 400 and the controller's code, as RWS answers a write without it
    assert modules(a) == ["MainModule"]
    master(a)
    with pytest.raises(ABBException, match="held by another client"):
        b._do_post("rw/mastership?action=request")
    with pytest.raises(ABBException, match="mastership is held by another client"):
        load(b, "IRB120Server.mod")
    with pytest.raises(ABBException, match="needs mastership"):
        b.resetpp()
    load(a, "IRB120Server.mod")
    assert modules(b) == ["MainModule", "IRB120Server"]
    a._do_post("rw/mastership?action=release")
    a._do_post("users/rmmp?action=cancel")  # and the manual-mode privilege it came with
    master(b)  # free again
    b._do_post("rw/rapid/tasks/T_ROB1?action=unloadmod", {"module": "IRB120Server"})
    assert modules(a) == ["MainModule"]
    b.close()  # logging out releases mastership
    master(a)


# docs/real_robot.md, section 1: which files load with which options (the emulator's load-time check over RWS)
MATRIX = [
    ("", ["IRB120Serial.mod"], None),
    ("", ["IRB120Socket.mod"], "socketdev needs RobotWare option 616-1 PC Interface or 672-1 Socket Messaging"),
    ("616-1", ["IRB120Socket.mod"], None),
    ("672-1", ["IRB120Socket.mod"], None),
    ("608-1", ["IRB120Socket.mod"], "socketdev needs RobotWare option 616-1"),
    ("608-1", ["IRB120Serial.mod", "IRB120Zone.sys"], None),
    ("616-1", ["IRB120Serial.mod", "IRB120Zone.sys"], "wzstationary needs RobotWare option 608-1 World Zones"),
    ("616-1,608-1", ["IRB120Socket.mod", "IRB120Zone.sys"], None),
    ("616-1,608-1", ["IRB120Serial.mod", "IRB120Socket.mod"], "ambiguous"),
]


@pytest.mark.parametrize("options,files,refusal", MATRIX)
def test_the_option_matrix_holds_for_modules_loaded_over_rws(rws_emulator, options, files, refusal):
    emu = rws_emulator(options=options)
    r = RWS(emu.url)
    files = ["IRB120Server.mod", *files]
    upload(r, *files)
    master(r)
    for i, f in enumerate(files):
        if refusal and i == len(files) - 1:
            with pytest.raises(ABBException, match="was not loaded: see the event log") as e:
                load(r, f)
            assert e.value.code == -400
            newest = r.read_event_log()[0]
            assert newest.msgtype == 3 and refusal.lower() in newest.desc.lower(), newest
            assert f"$HOME/IRB120/{f}" in newest.desc
            assert modules(r) == ["MainModule"] + [p.split(".")[0] for p in files[:-1]]
        else:
            load(r, f)
    if not refusal:
        assert modules(r) == ["MainModule"] + [p.split(".")[0] for p in files]


def test_a_syntax_error_s_line_reaches_the_event_log(rws_emulator):
    emu = rws_emulator()
    r = RWS(emu.url)
    broken = rapid_file("IRB120Serial.mod").read_text().replace("ENDPROC", "ENDPROC )", 1)
    line = next(i for i, t in enumerate(broken.splitlines(), 1) if "ENDPROC )" in t)
    upload(r, "IRB120Serial.mod", text={"IRB120Serial.mod": broken})
    master(r)
    with pytest.raises(ABBException, match="not loaded"):
        load(r, "IRB120Serial.mod")
    event = r.read_event_log()[0]
    assert event.title == "Syntax error" and f"line {line}, column 13: unexpected ')'" in event.desc, event
    assert modules(r) == ["MainModule"]


def test_remote_start_needs_auto_and_the_motors_on(rws_emulator):
    emu = rws_emulator(op_mode="manual_reduced")
    r = RWS(emu.url)
    master(r)
    with pytest.raises(ABBException, match="remote start needs AUTO") as e:
        r.start()
    assert e.value.code == -403
    with pytest.raises(ABBException, match="enabling device"):
        r.set_controller_state("motoron")
    emu.controller.op_mode = "auto"
    with pytest.raises(ABBException, match="motors are off"):
        r.start()
    assert r.get_execution_state().ctrlexecstate == "stopped"


def test_the_command_line_serves_rws_on_loopback_only():
    cmd = [sys.executable, "-m", "maniskill_irb120", "emulator"]
    bad = subprocess.run([*cmd, "--rws", "0.0.0.0:8080"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "serves 127.0.0.1:PORT only" in bad.stderr
    proc = subprocess.Popen([*cmd, "--rws", "127.0.0.1:0", "--options", "608-1"], stdout=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:")
        r = RWS(url)
        assert [s["option"] for s in r._do_get("rw/system")["_embedded"]["_state"][1:]] == ["608-1 World Zones"]
        r.close()
    finally:
        proc.terminate()
        proc.wait(10)


def test_a_module_whose_data_cannot_be_set_up_is_refused_and_the_server_serves_on(rws_emulator):
    emu = rws_emulator()
    r = RWS(emu.url)
    upload(r, "Bad.mod", text={"Bad.mod": "MODULE Bad\n  VAR byte b := 300;\nENDMODULE\n"})
    master(r)
    with pytest.raises(ABBException, match="not loaded"):
        load(r, "Bad.mod")
    event = r.read_event_log()[0]
    assert event.msgtype == 3 and "b is a byte (0..255) and cannot take 300" in event.desc and "line 2" in event.desc
    assert modules(r) == ["MainModule"]
    with pytest.raises(ABBException, match="lists persistents only"):
        r._do_post("rw/rapid/symbols?action=search-symbols", {"symtyp": "var"})
    assert r.get_rapid_variables() == []  # the stock MainModule has none


def test_nothing_is_loaded_unloaded_or_moved_while_the_program_runs(rws_emulator):
    emu = rws_emulator()
    r = RWS(emu.url)
    upload(r, "IRB120Server.mod", "IRB120Serial.mod")
    master(r)
    load(r, "IRB120Server.mod")
    load(r, "IRB120Serial.mod")
    r._do_post("rw/rapid/tasks/T_ROB1/pcp?action=set-pp-routine", {"routine": "IRB120Server"})
    emu.controller.start(remote=False)  # the operator, on the pendant
    assert r.get_execution_state().ctrlexecstate == "running"
    for call in (
        lambda: load(r, "IRB120Serial.mod"),
        lambda: r._do_post("rw/rapid/tasks/T_ROB1?action=unloadmod", {"module": "IRB120Serial"}),
        lambda: r.resetpp(),
    ):
        with pytest.raises(ABBException, match="the program is running; stop it first") as e:
            call()
        assert e.value.code == -409
    assert modules(r) == ["MainModule", "IRB120Server", "IRB120Serial"]
    assert r._do_get("rw/rapid/tasks/T_ROB1/pcp")["_embedded"]["_state"][0]["routinename"] == "IRB120Server"
    r.stop()
    assert r.get_execution_state().ctrlexecstate == "stopped"
    r.resetpp()  # stopped: PP to main runs the program's UNDO handlers, then stands at the main entry
    assert r._do_get("rw/rapid/tasks/T_ROB1/pcp")["_embedded"]["_state"][0]["routinename"] == "main"
    assert any(e.title == "PP to main" for e in r.read_event_log())

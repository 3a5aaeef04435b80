"""What a real IRC5's Robot Web Services refuse, refused by the emulator too (issue 89, "In the emulator"): RMMP
before mastership in the manual modes, the key switch taking mastership and stopping the program, mastership of
a vanished client ending with its session, PERS kept across loads of other modules, no program pointer at a PROC
with parameters, no value for a non-value type, writes without mastership answered 400 with the controller's
code, nested folders. Each test fails on the emulator as it was before its rule. The findings about the HTTP
server itself (sessions, the file service, malformed requests, SIGTERM) are in test_rws_server.py."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
rws_client = pytest.importorskip("abb_robot_client.rws")

from maniskill_irb120.abb.emulator import rws as rws_mod  # noqa: E402
from maniskill_irb120.abb.emulator.rws import CODE_NO_MASTERSHIP, RWSEmulator  # noqa: E402

ABBException, RWS = rws_client.ABBException, rws_client.RWS

SPIN = """MODULE Spin
    PERS num count := 0;
    PROC spin()
        WHILE TRUE DO
            count := count + 1;
            WaitTime 0.02;
        ENDWHILE
    ENDPROC
ENDMODULE
"""


def put(r, name: str, text: str) -> None:
    if "IRB120" not in r.list_files("$HOME"):
        r._do_post("fileservice/$HOME", {"fs-action": "create", "fs-newname": "IRB120"})
    r.upload_file(f"$HOME/IRB120/{name}", text.encode())


def load(r, name: str) -> None:
    r._do_post("rw/rapid/tasks/T_ROB1?action=loadmod", {"modulepath": f"$HOME/IRB120/{name}", "replace": "true"})


def poll(r) -> str:
    return r._do_get("users/rmmp/poll")["_embedded"]["_state"][0]["status"]


def rmmp(r) -> dict:
    return r._do_get("users/rmmp")["_embedded"]["_state"][0]


def wait_poll(r, until: set[str], limit_s: float = 2.0) -> str:
    deadline = time.monotonic() + limit_s
    while (status := poll(r)) not in until and time.monotonic() < deadline:
        time.sleep(0.05)
    return status


def test_manual_mode_mastership_needs_rmmp_the_operator_grants(rws_emulator):
    """RWS 1.0 reference, mastership request: "In manual mode, mastership can be gained after getting RMMP"."""
    emu = rws_emulator()  # manual reduced speed, the operator grants
    r = RWS(emu.url)
    with pytest.raises(ABBException, match="needs RMMP") as e:
        r._do_post("rw/mastership?action=request")
    assert e.value.code == -403 and "POST /users/rmmp" in str(e.value)
    assert emu.controller.master is None
    assert rmmp(r)["privilege"] == "none"
    raw = r._session.post(f"{emu.url}/users/rmmp?json=1", {"privilege": "modify"}, auth=r.auth)
    assert raw.status_code == 202
    state = rmmp(r)
    assert state["privilege"] == "pending modify" and int(state["userid"]) > 0
    assert poll(r) == "PENDING"
    assert wait_poll(r, {"GRANTED", "REJECTED"}) == "GRANTED"
    assert rmmp(r)["privilege"] == "modify"
    with pytest.raises(ABBException, match="local client"):  # nobody answers their own request remotely
        r._do_post("users/rmmp?action=set", {"uid": state["userid"], "privilege": "modify"})
    r._do_post("rw/mastership?action=request")
    assert emu.controller.master is not None
    r._do_post("users/rmmp?action=cancel")
    assert rmmp(r)["privilege"] == "none" and emu.controller.master is None
    with pytest.raises(ABBException, match="privilege="):
        r._do_post("users/rmmp", {"privilege": "everything"})


def test_rmmp_is_for_the_manual_modes_only(rws_emulator):
    emu = rws_emulator(op_mode="auto")
    r = RWS(emu.url)
    with pytest.raises(ABBException, match="RMMP is for the manual modes") as e:
        r._do_post("users/rmmp", {"privilege": "modify"})
    assert e.value.code == -400
    r._do_post("rw/mastership?action=request")  # in AUTO mastership needs no RMMP
    assert emu.controller.master is not None


def test_a_denied_an_unanswered_and_a_hand_answered_rmmp_request(rws_emulator, monkeypatch):
    monkeypatch.setattr(rws_mod, "RMMP_TIMEOUT_S", 1.0)  # RWS's 10 s, shortened
    r = RWS(rws_emulator(operator="deny").url)
    r._do_post("users/rmmp", {"privilege": "modify"})
    assert wait_poll(r, {"GRANTED", "REJECTED"}) == "REJECTED"
    with pytest.raises(ABBException, match="needs RMMP"):
        r._do_post("rw/mastership?action=request")

    emu = rws_emulator(operator="absent")
    a, b = RWS(emu.url), RWS(emu.url)
    assert poll(a) == "NO SUCH REQUEST"
    a._do_post("users/rmmp", {"privilege": "exec"})
    with pytest.raises(ABBException, match="holds or awaits RMMP"):  # one request at a time
        b._do_post("users/rmmp", {"privilege": "modify"})
    for _ in range(5):  # each poll keeps the request alive past the timeout
        time.sleep(0.3)
        assert poll(a) == "PENDING"
    time.sleep(1.3)  # no poll: the request lapses
    assert poll(a) == "REJECTED" and rmmp(a)["privilege"] == "none"
    b._do_post("users/rmmp", {"privilege": "modify"})
    emu.controller.answer_rmmp(grant=True)  # the operator, by hand
    assert poll(b) == "GRANTED"
    b._do_post("rw/mastership?action=request")
    b.close()  # the session ends: its RMMP and mastership go
    assert emu.controller.rmmp is None and emu.controller.master is None
    a._do_post("users/rmmp", {"privilege": "modify"})
    emu.controller.answer_rmmp(grant=True)
    a._do_post("rw/mastership?action=request")


def test_turning_the_key_to_manual_revokes_mastership_and_rmmp(rws_emulator):
    """Finding 8 (the key's part) and the RMMP contract: AUTO -> manual takes remote mastership; manual -> AUTO
    takes RMMP (it exists only in manual)."""
    emu = rws_emulator(op_mode="auto")
    r = RWS(emu.url)
    put(r, "Spin.mod", SPIN)
    r._do_post("rw/mastership?action=request")
    emu.controller.op_mode = "manual_reduced"
    assert emu.controller.master is None
    with pytest.raises(ABBException, match="needs mastership"):
        load(r, "Spin.mod")
    r._do_post("users/rmmp", {"privilege": "modify"})
    assert wait_poll(r, {"GRANTED", "REJECTED"}) == "GRANTED"
    emu.controller.op_mode = "auto"
    assert rmmp(r)["privilege"] == "none" and poll(r) != "GRANTED"


def test_a_vanished_client_s_mastership_ends_with_its_session(rws_emulator):
    """Finding 8: the client that held mastership never logs out; once its session lapses the next client gets
    mastership (abb-robot-client's clients are sessions; RobotWare ends an idle one)."""
    emu = rws_emulator(op_mode="auto", session_idle_s=1.0)
    gone, next_client = RWS(emu.url), RWS(emu.url)
    gone._do_post("rw/mastership?action=request")  # and then it crashes: no logout
    with pytest.raises(ABBException, match="held by another client"):
        next_client._do_post("rw/mastership?action=request")
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:  # the next client keeps its own session alive, the first one's lapses
        next_client.get_operation_mode()
        time.sleep(0.1)
    next_client._do_post("rw/mastership?action=request")
    assert emu.controller.master is not None


def test_turning_the_key_from_auto_to_manual_stops_the_program_and_the_motors(rws_emulator):
    """Finding 9: the key from AUTO to MANR while the program runs: an IRC5 stops it and the motors go off."""
    emu = rws_emulator(op_mode="auto")
    r = RWS(emu.url)
    put(r, "Spin.mod", SPIN)
    r._do_post("rw/mastership?action=request")
    load(r, "Spin.mod")
    r._do_post("rw/rapid/tasks/T_ROB1/pcp?action=set-pp-routine", {"routine": "spin"})
    r.set_controller_state("motoron")
    r.start()
    time.sleep(0.2)
    assert r.get_execution_state().ctrlexecstate == "running"
    emu.controller.op_mode = "manual_reduced"
    assert r.get_execution_state().ctrlexecstate == "stopped"
    assert r.get_controller_state() == "motoroff"
    counted = float(r.get_rapid_variable("Spin/count"))
    time.sleep(0.2)
    assert float(r.get_rapid_variable("Spin/count")) == counted  # it does not run on


PERS_A = "MODULE ModA\n    PERS num answer := 0;\n    PERS num load := 1;\nENDMODULE\n"
PERS_B = "MODULE ModB\n    PERS num other := 7;\nENDMODULE\n"


def test_loading_another_module_keeps_the_current_values_of_pers(rws_emulator):
    """Finding 10: a PERS's current value lives in its module; loading or unloading another module leaves it
    (42 stays 42, a load of 2.5 stays 2.5); loading the module itself again with replace gives its file's
    values."""
    emu = rws_emulator(op_mode="auto")
    r = RWS(emu.url)
    put(r, "ModA.mod", PERS_A)
    put(r, "ModB.mod", PERS_B)
    r._do_post("rw/mastership?action=request")
    load(r, "ModA.mod")
    r.set_rapid_variable("ModA/answer", "42")
    r.set_rapid_variable("ModA/load", "2.5")
    load(r, "ModB.mod")
    assert r.get_rapid_variable("ModA/answer") == "42" and r.get_rapid_variable("ModA/load") == "2.5"
    r.set_rapid_variable("ModB/other", "8")
    r._do_post("rw/rapid/tasks/T_ROB1?action=unloadmod", {"module": "ModB"})
    assert r.get_rapid_variable("ModA/answer") == "42"
    load(r, "ModB.mod")
    assert r.get_rapid_variable("ModB/other") == "7"  # loaded anew: its file's value
    load(r, "ModA.mod")
    assert r.get_rapid_variable("ModA/answer") == "0" and r.get_rapid_variable("ModA/load") == "1"


ODD = """MODULE Odd
    VAR iodev dev;
    VAR clock clk;
    PROC withArgs(num x)
        TPWrite "x";
    ENDPROC
    PROC plain()
        ClkStart clk;
    ENDPROC
ENDMODULE
"""


def test_no_pp_at_a_proc_with_parameters_and_no_value_for_non_value_types(rws_emulator):
    """Finding 12: the program pointer goes to a PROC without parameters only; an iodev takes no num; a clock
    is not read as a Python repr."""
    emu = rws_emulator(op_mode="auto")
    r = RWS(emu.url)
    put(r, "Odd.mod", ODD)
    r._do_post("rw/mastership?action=request")
    load(r, "Odd.mod")
    with pytest.raises(ABBException, match="takes parameters") as e:
        r._do_post("rw/rapid/tasks/T_ROB1/pcp?action=set-pp-routine", {"routine": "withArgs"})
    assert e.value.code == -400
    assert r._do_get("rw/rapid/tasks/T_ROB1/pcp")["_embedded"]["_state"][0]["routinename"] == ""
    r._do_post("rw/rapid/tasks/T_ROB1/pcp?action=set-pp-routine", {"routine": "plain"})
    with pytest.raises(ABBException, match="iodev, a non-value data type"):
        r.set_rapid_variable("Odd/dev", "3")
    with pytest.raises(ABBException, match="clock, a non-value data type"):
        r.get_rapid_variable("Odd/clk")
    with pytest.raises(ABBException, match="non-value"):
        r.set_rapid_variable("Odd/clk", "0")


def test_a_write_without_mastership_is_400_with_the_controller_s_code(rws_emulator):
    """RWS 1.0 reference, "RobotWare return codes service": a RAPID variable set without mastership gets 400 and
    code -1073414146 (the emulator answered 403 with its own code)."""
    emu = rws_emulator(operator="absent")
    r = RWS(emu.url)
    put(r, "ModA.mod", PERS_A)
    r._do_post("users/rmmp", {"privilege": "modify"})
    emu.controller.answer_rmmp(grant=True)
    r._do_post("rw/mastership?action=request")
    load(r, "ModA.mod")
    r._do_post("rw/mastership?action=release")
    for call in (
        lambda: r.set_rapid_variable("ModA/answer", "42"),
        lambda: load(r, "ModA.mod"),
        lambda: r.resetpp(),
    ):
        with pytest.raises(ABBException, match="needs mastership") as e:
            call()
        assert e.value.code == CODE_NO_MASTERSHIP
    raw = r._session.post(
        f"{emu.url}/rw/rapid/symbol/data/RAPID/T_ROB1/ModA/answer?action=set&json=1", {"value": "1"}, auth=r.auth
    )
    assert raw.status_code == 400 and raw.json()["_embedded"]["status"]["code"] == CODE_NO_MASTERSHIP


def test_nested_folders_are_created_in_one_request(rws_emulator):
    """RWS's fs-newname takes a path (a/b); the emulator refused it."""
    r = RWS(rws_emulator().url)
    r._do_post("fileservice/$HOME", {"fs-action": "create", "fs-newname": "a/b"})
    assert r.list_files("$HOME/a") == ["b"]
    for bad in ("a/../c", "/", "a//b"):
        with pytest.raises(ABBException, match="fs-newname"):
            r._do_post("fileservice/$HOME", {"fs-action": "create", "fs-newname": bad})


def test_the_operator_is_one_of_three():
    with pytest.raises(ValueError, match="operator="):
        RWSEmulator(operator="maybe")

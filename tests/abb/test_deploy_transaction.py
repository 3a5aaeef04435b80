"""``maniskill-irb120 deploy`` as a transaction, run as an integrator runs it (a separate process) against the
emulator's Robot Web Services: what is loaded is what it reports, a failed or interrupted deploy puts the earlier
deployment back, a refused one writes nothing, the manual modes need the operator's grant, ``unload`` removes only
what deploy wrote, and an option list in another documented shape is read, not taken for "no options"."""

from __future__ import annotations

import json
import os
import pty
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
pytest.importorskip("abb_robot_client")

from abb_robot_client.rws import RWS  # noqa: E402

from maniskill_irb120.abb import deploy as dep  # noqa: E402
from maniskill_irb120.abb.emulator.rws import RWSEmulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def cli(*argv: str, timeout: float = 120, stdin=subprocess.DEVNULL) -> subprocess.CompletedProcess:
    """``maniskill-irb120 deploy ARGV`` in its own process, as an integrator types it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-m", "maniskill_irb120.cli", "deploy", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=stdin,
        env=env,
    )


def deployed(emu: RWSEmulator) -> bool:
    """A first deployment, in this process (what a test starts from; the deploy under test runs in its own)."""
    from maniskill_irb120.cli import main

    return main(["deploy", "--controller", emu.url, "--yes"]) == 0


def snapshot(emu: RWSEmulator) -> tuple:
    """What a deployment may change: the task's modules, $HOME's files and their bytes, PP, the program state."""
    vc = emu.controller
    files = {str(p.relative_to(vc.home)): p.read_bytes() if p.is_file() else None for p in vc.home.rglob("*")}
    return [m.name for m in vc.modules.values()], files, vc.pcp(), vc.exec_state


def manifest(emu: RWSEmulator) -> dict:
    return json.loads((emu.controller.home / "IRB120" / dep.MANIFEST).read_text())


def edited(tmp_path: Path, name: str, **consts: str) -> Path:
    """A --rapid-dir with the serial build's files, the constants ``consts`` set as given."""
    d = tmp_path / name
    d.mkdir()
    for f in ("IRB120Server.mod", "IRB120Serial.mod"):
        text = (dep.shipped_rapid_dir() / f).read_text()
        for k, v in consts.items():
            text, n = re.subn(rf"(CONST \w+ {k} := )[^;]+;", rf"\g<1>{v};", text)
            assert n <= 1
        (d / f).write_text(text)
    return d


def loaded_constant(emu: RWSEmulator, module: str, name: str) -> str:
    return emu.controller.symbol([dep.TASK, module, name])[0]


def test_two_deploys_at_once_each_report_what_was_loaded(rws_emulator, tmp_path):
    """Finding 1: both uploaded to one folder before taking mastership, so one reported FALSE while TRUE was
    loaded. Now each takes mastership first, uploads to its own folder and reads back what it loaded."""
    emu = rws_emulator(op_mode="auto")
    dirs = {v: edited(tmp_path, v.lower(), ALLOW_AUTO=v) for v in ("FALSE", "TRUE")}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    procs = {
        v: subprocess.Popen(
            [sys.executable, "-m", "maniskill_irb120.cli", "deploy", "--controller", emu.url, "--yes"]
            + ["--rapid-dir", str(d)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for v, d in dirs.items()
    }
    ended = {}
    outs = {}
    while len(ended) < 2:
        for v, p in procs.items():
            if v not in ended and p.poll() is not None:
                ended[v] = time.monotonic()
                outs[v] = p.communicate()
        time.sleep(0.05)
    for v, (out, err) in outs.items():
        assert procs[v].returncode == 0, err
        assert re.search(rf"loaded IRB120Server, IRB120Serial into T_ROB1; read back: .*ALLOW_AUTO = {v}\b", out), out
    last = max(ended, key=ended.get)
    assert loaded_constant(emu, "IRB120Server", "ALLOW_AUTO") == last
    assert f"deployment {manifest(emu)['active']} is active" in outs[last][0]
    assert len(manifest(emu)["deployments"]) == 1  # the first one's folder is gone with its switch-over


def test_what_is_loaded_is_read_back_and_a_mismatch_is_rolled_back(rws_emulator, tmp_path):
    """Finding 1, the check itself: a file changed on the controller between upload and load (another writer)
    is caught by reading the loaded module's settings back, and the earlier deployment is put back."""
    emu = rws_emulator(op_mode="auto")
    assert deployed(emu)  # the working deployment the finding starts from
    before = snapshot(emu)
    c = dep.connect(emu.url)
    real_load = c.load_module

    tampered: list[str] = []

    def load_after_a_foreign_write(path: str, replace: bool = True) -> None:
        if path.endswith("IRB120Server.mod") and not tampered:  # the new upload, once (not the rollback's reload)
            tampered.append(path)
            f = emu.controller.file_path(path)
            f.write_text(f.read_text().replace("ALLOW_AUTO := FALSE", "ALLOW_AUTO := TRUE"))
        real_load(path, replace)

    c.load_module = load_after_a_foreign_write
    lines: list[str] = []
    with pytest.raises(dep.DeployRefused) as e:
        dep.deploy(c, lines.append, lambda q: True)
    c.close()
    msg = str(e.value)
    assert "IRB120Server/ALLOW_AUTO reads back as TRUE from the controller, but the uploaded file sets FALSE" in msg
    assert "reloaded IRB120Server, IRB120Serial from $HOME/IRB120/" in msg
    assert "program pointer back at IRB120Server/IRB120Server" in msg
    assert snapshot(emu) == before


def test_a_typo_in_a_redeployed_module_leaves_the_working_server_loaded(rws_emulator, tmp_path):
    """Finding 2: a syntax error used to unload the working modules, overwrite their files and lose PP."""
    emu = rws_emulator(op_mode="auto")
    assert deployed(emu)  # the working deployment the finding starts from
    before = snapshot(emu)
    broken = edited(tmp_path, "broken")
    text = (broken / "IRB120Serial.mod").read_text()
    (broken / "IRB120Serial.mod").write_text(text.replace("ENDPROC", "ENDPROC )", 1))
    r = cli("--controller", emu.url, "--yes", "--rapid-dir", str(broken))
    assert r.returncode == 1
    assert "IRB120Serial.mod into T_ROB1 failed" in r.stderr and "controller event: Syntax error" in r.stderr
    assert "unloaded IRB120Server\n" in r.stderr
    assert "reloaded IRB120Server, IRB120Serial from $HOME/IRB120/" in r.stderr
    active = manifest(emu)["active"]
    assert f"the controller holds IRB120Server, IRB120Serial (deployment {active}, files in" in r.stderr
    assert "PP at IRB120Server/IRB120Server" in r.stderr
    assert snapshot(emu) == before  # modules, every file byte for byte, PP


def test_a_deploy_refused_for_mastership_writes_nothing(rws_emulator):
    """Finding 3: refused only after uploading, it left files that differ from what is loaded."""
    emu = rws_emulator(op_mode="auto")
    assert deployed(emu)  # the working deployment the finding starts from
    hmi = RWS(emu.url)
    hmi._do_post("rw/mastership?action=request")  # an HMI holds mastership
    before = snapshot(emu)
    r = cli("--controller", emu.url, "--yes", "--channel", "serial", "--mastership-wait", "1")
    assert r.returncode == 1 and "requesting mastership" in r.stderr and "nothing was changed" in r.stderr, r.stderr
    assert snapshot(emu) == before
    hmi._do_post("rw/mastership?action=release")
    hmi.close()


def test_the_manual_modes_need_the_operators_grant_and_auto_asks_none(rws_emulator, capsys):
    """Finding 4: deploy never asked for RMMP, so on a real IRC5 the documented flow (deploy, then Start in MANR)
    failed at "requesting mastership"; the emulator, which gave mastership anyway, now refuses it without RMMP."""
    emu = rws_emulator(operator="deny")  # manual reduced speed; the operator rejects remote access
    before = snapshot(emu)
    r = cli("--controller", emu.url, "--yes")
    assert r.returncode == 1 and "the operator did not grant remote access on the FlexPendant" in r.stderr, r.stderr
    assert "nothing was changed" in r.stderr and snapshot(emu) == before
    emu.controller.operator = "grant"
    r = cli("--controller", emu.url, "--yes")
    assert r.returncode == 0, r.stderr
    assert "manual mode: waiting up to 60 s for the operator" in r.stdout
    assert "remote access granted on the FlexPendant" in r.stdout
    assert emu.controller.pcp() == ("IRB120Server", "IRB120Server")
    assert emu.controller.master is None and emu.controller.rmmp_state(None)["privilege"] == "none"
    emu.controller.op_mode = "auto"
    from maniskill_irb120.cli import main

    capsys.readouterr()
    assert main(["deploy", "unload", "--controller", emu.url]) == 0
    assert "remote access" not in capsys.readouterr().out


def test_unload_removes_only_what_deploy_wrote_and_leaves_the_operators_pp(rws_emulator, tmp_path):
    """Finding 5: unload deleted the integrator's files in $HOME/IRB120 and moved PP to main though nothing of
    ours held it."""
    emu = rws_emulator(op_mode="auto")
    vc = emu.controller
    (vc.home / "IRB120").mkdir()
    (vc.home / "IRB120" / "notes.txt").write_text("cell 3: gripper fingers replaced")
    (vc.home / "IRB120" / "backup").mkdir()
    (vc.home / "IRB120" / "backup" / "IRB120Server.mod").write_text("MODULE IRB120Server\nENDMODULE\n")
    theirs = {p: p.read_bytes() for p in (vc.home / "IRB120").rglob("*") if p.is_file()}
    assert deployed(emu)  # the working deployment the finding starts from
    r = cli("unload", "--controller", emu.url)
    assert r.returncode == 0, r.stderr
    assert "left what deploy did not write: backup, notes.txt" in r.stdout
    assert {p: p.read_bytes() for p in (vc.home / "IRB120").rglob("*") if p.is_file()} == theirs
    assert sorted(p.name for p in (vc.home / "IRB120").iterdir()) == ["backup", "notes.txt"]
    # the operator's own routine holds PP, nothing of ours is loaded: unload leaves it there
    op = vc.home / "Calib.mod"
    op.write_text('MODULE Calib\n    PROC calib()\n        TPWrite "calibrating";\n    ENDPROC\nENDMODULE\n')
    vc.master = "operator"
    vc.load_module("operator", "$HOME/Calib.mod", True)
    vc.set_pp("operator", "calib")
    vc.master = None
    r = cli("unload", "--controller", emu.url)
    assert r.returncode == 0, r.stderr
    assert (
        "unloaded nothing (none of ours was loaded)" in r.stdout and "program pointer left at Calib/calib" in r.stdout
    )
    assert vc.pcp() == ("Calib", "calib")


def test_ctrl_c_at_the_prompt_puts_the_earlier_deployment_back(rws_emulator, tmp_path):
    """Finding 6: Ctrl-C left a half-loaded task. Here it comes at the program-pointer prompt, after the new
    modules are loaded."""
    emu = rws_emulator(op_mode="auto")
    assert deployed(emu)  # the working deployment the finding starts from
    before = snapshot(emu)
    c = dep.connect(emu.url)

    def ctrl_c(question: str) -> bool:
        raise KeyboardInterrupt

    with pytest.raises(dep.DeployRefused) as e:
        dep.deploy(c, lambda m: None, ctrl_c, rapid_dir=edited(tmp_path, "new", ALLOW_AUTO="TRUE"))
    c.close()
    assert str(e.value).startswith("interrupted (Ctrl-C)\nrolled back to what this deploy found:")
    assert snapshot(emu) == before
    assert emu.controller.master is None


def test_a_killed_deploy_is_recovered_by_the_next_one(rws_emulator, tmp_path):
    """Finding 6: a killed deploy left mastership held and a half-loaded task, and then deploy and unload both
    failed. The next deploy waits for the dead client's mastership to be released (its session ends), finds the
    unfinished deployment in the manifest, rolls it back, and deploys."""
    emu = rws_emulator(op_mode="auto", session_idle_s=8.0)  # long enough for a loaded machine between requests
    assert deployed(emu)  # the working deployment the finding starts from
    before = snapshot(emu)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    leader, follower = pty.openpty()  # a terminal, so that deploy stops at its prompt (and shows it)
    proc = subprocess.Popen(
        [sys.executable, "-m", "maniskill_irb120.cli", "deploy", "--controller", emu.url]
        + ["--rapid-dir", str(edited(tmp_path, "new", ALLOW_AUTO="TRUE"))],
        stdin=follower,
        stdout=follower,
        stderr=follower,
        env=env,
    )
    os.close(follower)
    seen = b""
    deadline = time.monotonic() + 90
    while b"[y/N]" not in seen and time.monotonic() < deadline and proc.poll() is None:
        try:
            seen += os.read(leader, 4096) if _readable(leader) else b""
        except OSError:  # the process closed its terminal: it ended, and the assert below shows what it said
            break
        time.sleep(0.05)
    assert b"[y/N]" in seen, seen.decode(errors="replace")
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    os.close(leader)
    assert manifest(emu)["pending"] is not None and emu.controller.master is not None
    assert loaded_constant(emu, "IRB120Server", "ALLOW_AUTO") == "TRUE"  # half-way: the new modules, no PP
    r = cli("unload", "--controller", emu.url, "--mastership-wait", "30")
    assert r.returncode == 0, r.stderr
    assert "was interrupted before it finished: rolling it back" in r.stdout
    assert "reloaded IRB120Server, IRB120Serial" in r.stdout
    assert deployed(emu)
    assert snapshot(emu)[0] == before[0] and snapshot(emu)[2] == before[2]


def _readable(fd: int) -> bool:
    import select

    return bool(select.select([fd], [], [], 0.1)[0])


# ---------------------------------------------------------------- finding 7: option lists in other shapes
SYSTEM_605 = {  # RobotWare 6.05's /rw/system as JSON: the options nested in a sys-options-li item
    "_embedded": {
        "_state": [
            {"_type": "sys-system-li", "_title": "system", "name": "6.05.0047", "rwversion": "6.05.0047",
             "rwversionname": "6.05.00.00 Internal build 0047"},
            {"_type": "sys-options-li", "_title": "options", "options": [
                {"_type": "sys-option-li", "_title": "0", "option": "RobotWare Base"},
                {"_type": "sys-option-li", "_title": "1", "option": "English"},
                {"_type": "sys-option-li", "_title": "3", "option": "616-1 PC Interface"},
                {"_type": "sys-option-li", "_title": "5", "option": "623-1 Multitasking"},
                {"_type": "sys-option-li", "_title": "6", "option": "608-1 World Zones"},
            ]},
        ]
    }
}  # fmt: skip


def test_the_option_list_is_read_in_every_known_shape_and_an_unknown_one_is_refused():
    flat = {"_embedded": {"_state": [{"_type": "sys-system-li"}, {"_type": "sys-option-li", "option": "672-1 x"}]}}
    endpoint = {"_embedded": {"_state": [{"_type": "sys-option-li", "_title": "0", "option": "608-1 World Zones"}]}}
    bare = {"_embedded": {"_state": [{"_type": "sys-system-li", "name": "x"}]}}
    assert dep.option_ids(dep.option_texts(SYSTEM_605)) == ["616-1", "623-1", "608-1"]
    assert dep.option_ids(dep.option_texts(flat)) == ["672-1"]
    assert dep.option_ids(dep.option_texts(bare, endpoint)) == ["608-1"]
    assert dep.option_texts(bare, {"_embedded": {"_state": []}}) == []  # the options resource: none installed
    assert dep.option_texts(bare) is None and dep.option_texts(bare, {"x": 1}) is None


def test_a_robotware_605_answer_picks_the_tcp_build_with_the_zone_and_an_unknown_shape_is_refused(rws_emulator):
    """Finding 7: read as "no options", the 6.05 answer made deploy pick the serial build and no zone."""
    emu = rws_emulator(op_mode="auto", options="616-1,608-1")  # answers /rw/system in the flat shape: replaced
    c = dep.connect(emu.url)
    real = c.system_answers
    c.system_answers = lambda: (SYSTEM_605, None)
    lines: list[str] = []
    dep.deploy(c, lines.append, lambda q: True)
    assert "picked the tcp build with the world zone:" in lines
    assert [m.name for m in emu.controller.modules.values()] == [
        "MainModule",
        "IRB120Server",
        "IRB120Socket",
        "IRB120Zone",
    ]
    before = snapshot(emu)
    odd = {"_embedded": {"_state": [{"_type": "sys-system-li", "rwversionname": "6.05"}, {"_type": "sys-lic"}]}}
    c.system_answers = lambda: (odd, None)
    with pytest.raises(dep.DeployRefused, match=r"could not find the installed options .*sys-lic"):
        dep.deploy(c, lines.append, lambda q: True)
    assert snapshot(emu) == before
    c.system_answers = real
    c.close()

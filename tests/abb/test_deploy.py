"""``maniskill-irb120 deploy`` against the emulator's Robot Web Services: for every option set of the matrix the
right files are loaded, or the refusal names the missing option; a module that does not load brings the
controller's own message to the user; a wrong password, a running program and AUTO without ALLOW_AUTO are refused
with nothing changed; ``unload`` leaves the controller as it found it."""

from __future__ import annotations

import json
import re

import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
pytest.importorskip("abb_robot_client")

from maniskill_irb120.abb import deploy as dep  # noqa: E402
from maniskill_irb120.abb.client import ABBRobot  # noqa: E402
from maniskill_irb120.abb.emulator.rapid import OPTIONS  # noqa: E402
from maniskill_irb120.abb.emulator.rws import RWSEmulator  # noqa: E402
from maniskill_irb120.cli import main  # noqa: E402


def run(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(["deploy", *argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def snapshot(emu: RWSEmulator) -> tuple:
    """What a deployment may change: the task's modules, $HOME's files, the program pointer, the program state."""
    vc = emu.controller
    files = sorted(str(p.relative_to(vc.home)) for p in vc.home.rglob("*"))
    return [m.name for m in vc.modules.values()], files, vc.pcp(), vc.exec_state


def active_folder(emu: RWSEmulator):
    """The folder of the deployment the manifest on the controller names active."""
    manifest = json.loads((emu.controller.home / "IRB120" / "deploy.json").read_text())
    return emu.controller.home / manifest["deployments"][manifest["active"]]["folder"]


# options -> the modules deploy loads (docs/real_robot.md, section 1)
EXPECTED = {
    "": ["IRB120Server", "IRB120Serial"],
    "616-1": ["IRB120Server", "IRB120Socket"],
    "672-1": ["IRB120Server", "IRB120Socket"],
    "608-1": ["IRB120Server", "IRB120Serial", "IRB120Zone"],
    "616-1,608-1": ["IRB120Server", "IRB120Socket", "IRB120Zone"],
    "672-1,608-1": ["IRB120Server", "IRB120Socket", "IRB120Zone"],
    "689-1,623-1": ["IRB120Server", "IRB120Serial"],  # options that give the server nothing
}


@pytest.mark.parametrize("options", list(EXPECTED))
def test_deploy_loads_what_the_options_allow(rws_emulator, capsys, options):
    emu = rws_emulator(options=options)
    rc, out, err = run(capsys, "--controller", emu.url, "--yes")
    assert rc == 0, err
    assert [m.name for m in emu.controller.modules.values()] == ["MainModule", *EXPECTED[options]]
    assert emu.controller.pcp() == ("IRB120Server", "IRB120Server")
    assert emu.controller.exec_state == "stopped"
    folder = active_folder(emu)
    files = sorted(p.name for p in folder.iterdir())
    assert files == sorted(f"{m}.sys" if m == "IRB120Zone" else f"{m}.mod" for m in EXPECTED[options])
    assert sorted(p.name for p in (emu.controller.home / "IRB120").iterdir()) == sorted([folder.name, "deploy.json"])
    # it says what it picked and why
    channel = "tcp" if "616-1" in options or "672-1" in options else "serial"
    assert f"picked the {channel} build" in out
    if channel == "tcp":
        sock = "616-1 PC Interface" if "616-1" in options else "672-1 Socket Messaging"
        assert f"as {sock} provides the socket API" in out
    else:
        assert "needs no option (no 616-1 or 672-1 installed)" in out
    zone = "608-1" in options
    assert ("IRB120Zone.sys: the controller-side world zone (608-1 World Zones installed)" in out) == zone
    assert "program pointer at IRB120Server/IRB120Server; the program is stopped" in out


@pytest.mark.parametrize(
    "options,flags,missing",
    [
        ("", ["--channel", "tcp"], "616-1 PC Interface or 672-1 Socket Messaging"),
        ("608-1", ["--channel", "tcp"], "616-1 PC Interface or 672-1 Socket Messaging"),
        ("", ["--zone", "on"], "608-1 World Zones"),
        ("616-1", ["--zone", "on"], "608-1 World Zones"),
    ],
)
def test_a_build_the_options_do_not_allow_is_refused_naming_the_option(rws_emulator, capsys, options, flags, missing):
    emu = rws_emulator(options=options)
    before = snapshot(emu)
    rc, _, err = run(capsys, "--controller", emu.url, "--yes", *flags)
    assert rc == 1 and "refused" in err and missing in err, err
    assert snapshot(emu) == before


def test_asked_for_builds_that_fit_are_loaded(rws_emulator, capsys):
    emu = rws_emulator(options="616-1,608-1")
    rc, out, err = run(capsys, "--controller", emu.url, "--yes", "--channel", "serial", "--zone", "off")
    assert rc == 0, err
    assert [m.name for m in emu.controller.modules.values()] == ["MainModule", "IRB120Server", "IRB120Serial"]
    assert "the serial build, as asked" in out and "no IRB120Zone.sys: as asked" in out


def test_the_option_names_agree_with_the_emulator_s_option_table():
    for opt, name in dep.OPTION_NAMES.items():
        assert OPTIONS[opt].name == name


def test_a_module_that_does_not_load_shows_the_controller_s_message(rws_emulator, capsys, tmp_path):
    for f in ("IRB120Server.mod", "IRB120Serial.mod"):
        (tmp_path / f).write_text((dep.shipped_rapid_dir() / f).read_text())
    text = (tmp_path / "IRB120Serial.mod").read_text()
    broken = text.replace("ENDPROC", "ENDPROC )", 1)
    line = next(i for i, t in enumerate(broken.splitlines(), 1) if "ENDPROC )" in t)
    (tmp_path / "IRB120Serial.mod").write_text(broken)
    emu = rws_emulator()
    rc, out, err = run(capsys, "--controller", emu.url, "--yes", "--rapid-dir", str(tmp_path))
    assert rc == 1
    m = re.search(r"loading (\$HOME/IRB120/[^/]+)/IRB120Serial.mod into T_ROB1 failed", err)
    assert m, err
    assert f"controller event: Syntax error: file {m[1]}/IRB120Serial.mod: line {line}, column 13" in err
    assert "rolled back to what this deploy found:\n  unloaded IRB120Server\n" in err
    assert "the controller holds none of our modules; PP at MainModule/main" in err
    assert [m.name for m in emu.controller.modules.values()] == ["MainModule"]
    assert "program pointer" not in out


def test_a_wrong_password_is_refused_and_nothing_changes(rws_emulator, capsys):
    emu = rws_emulator()
    before = snapshot(emu)
    rc, _, err = run(capsys, "--controller", emu.url, "--yes", "--password", "guess")
    assert rc == 1 and "refused the user name or password (HTTP 401)" in err, err
    assert snapshot(emu) == before


def test_deploy_while_the_program_runs_is_refused_and_nothing_changes(rws_emulator, capsys):
    emu = rws_emulator()
    assert run(capsys, "--controller", emu.url, "--yes")[0] == 0
    emu.controller.start(remote=False)  # the operator: enabling device held, Start on the FlexPendant
    with ABBRobot.connect(emu.controller.program_url, timeout=2.0) as robot:
        assert robot.state().error == 0
    before = snapshot(emu)
    assert before[3] == "running"
    for argv in (["--controller", emu.url, "--yes"], ["unload", "--controller", emu.url]):
        rc, _, err = run(capsys, *argv)
        assert rc == 1 and "the program is running: stop it first" in err, err
        assert snapshot(emu) == before
    rc, out, _ = run(capsys, "stop", "--controller", emu.url)
    assert rc == 0 and "program stopped" in out
    assert emu.controller.exec_state == "stopped"


def test_unload_leaves_the_controller_as_it_found_it(rws_emulator, capsys):
    emu = rws_emulator(options="616-1,608-1")
    before = snapshot(emu)
    assert before[:3] == (["MainModule"], [], ("MainModule", "main"))
    assert run(capsys, "--controller", emu.url, "--yes")[0] == 0
    emu.controller.start(remote=False)
    assert run(capsys, "stop", "--controller", emu.url)[0] == 0
    rc, out, err = run(capsys, "unload", "--controller", emu.url)
    assert rc == 0, err
    assert "unloaded IRB120Server, IRB120Socket, IRB120Zone" in out
    assert "program pointer at MainModule/main (the task's main entry; it stood in our IRB120Server)" in out
    assert re.search(
        r"removed \$HOME/IRB120 \((\S+)/IRB120Server.mod, \1/IRB120Socket.mod, \1/IRB120Zone.sys, deploy.json\)", out
    )
    assert snapshot(emu) == before
    rc, out, _ = run(capsys, "unload", "--controller", emu.url)  # nothing of ours: says so, changes nothing
    assert rc == 0 and "nothing (none of ours was loaded)" in out and "no $HOME/IRB120 to remove" in out
    assert snapshot(emu) == before


def test_without_confirmation_the_program_pointer_stays_unset(rws_emulator, capsys):
    emu = rws_emulator()
    rc, out, _ = run(capsys, "--controller", emu.url)  # pytest's stdin is no terminal, and no --yes
    assert rc == 0
    assert "not confirmed: no terminal to answer at (pass --yes in scripts)" in out
    assert "program pointer not set" in out
    assert emu.controller.pcp() is None
    assert [m.name for m in emu.controller.modules.values()] == ["MainModule", "IRB120Server", "IRB120Serial"]


def test_start_runs_only_in_auto_with_allow_auto_set_deliberately(rws_emulator, capsys, tmp_path):
    emu = rws_emulator(op_mode="manual_reduced")
    assert run(capsys, "--controller", emu.url, "--yes")[0] == 0
    rc, _, err = run(capsys, "start", "--controller", emu.url, "--yes")
    assert rc == 1 and "started remotely in AUTO only" in err and "presses Start on the FlexPendant" in err
    emu.controller.op_mode = "auto"
    rc, _, err = run(capsys, "start", "--controller", emu.url, "--yes")
    assert rc == 1 and "refused to start in AUTO: ALLOW_AUTO is FALSE" in err, err
    assert emu.controller.exec_state == "stopped" and emu.controller.ctrl_state == "motoroff"
    # an integrator's deliberate change, deployed
    for f in ("IRB120Server.mod", "IRB120Serial.mod"):
        (tmp_path / f).write_text((dep.shipped_rapid_dir() / f).read_text())
    core = (tmp_path / "IRB120Server.mod").read_text()
    assert core.count("LOCAL CONST bool ALLOW_AUTO := FALSE;") == 1
    (tmp_path / "IRB120Server.mod").write_text(core.replace("ALLOW_AUTO := FALSE", "ALLOW_AUTO := TRUE"))
    rc, out, err = run(capsys, "--controller", emu.url, "--yes", "--rapid-dir", str(tmp_path))
    assert rc == 0 and "ALLOW_AUTO = TRUE" in out, err
    rc, out, err = run(capsys, "start", "--controller", emu.url, "--yes")
    assert rc == 0 and "program running" in out, err
    with ABBRobot.connect(emu.controller.program_url, timeout=2.0) as robot:
        assert robot.state().error == 0
    rc, out, _ = run(capsys, "status", "--controller", emu.url)
    assert rc == 0
    assert "operating mode AUTO, controller state motoron, program running" in out
    assert "speed ratio 100 %" in out and "program pointer: IRB120Server/IRB120Server" in out
    assert "Program started" in out
    assert run(capsys, "stop", "--controller", emu.url)[0] == 0


def test_bad_flags_are_named(capsys):
    assert main(["deploy"]) == 2
    assert "--controller http://HOST is required" in capsys.readouterr().err
    assert main(["deploy", "--controller", "http://127.0.0.1:1", "--channel", "wifi"]) == 2
    assert "--channel auto|serial|tcp" in capsys.readouterr().err
    rc, _, err = run(capsys, "--controller", "https://192.0.2.1")
    assert rc == 1 and "RobotWare 7 / OmniCore serves RWS 2.0" in err
    with pytest.raises(ValueError, match="channel='wifi'"):
        dep.choose_files([], channel="wifi")

"""The link under attack: stale or broken commands against the emulator running the shipped RAPID files (core,
channel module, world zone), byte by byte as a PC sends them, with the pendant driven in process. "Stale" is a
command sent before a stop or by a client that has gone: it never moves the robot. A corrupted frame costs only
itself, the watchdog is never delayed by a frame under way, a session start is a clean slate for a new client,
and the robot moves again after PP to main. Each test names the finding of the original report it holds."""

from __future__ import annotations

import io
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")

from maniskill_irb120.abb.client import (  # noqa: E402
    CONNECT_WAIT_S,
    ABBRobot,
    ControllerStopped,
    RobotTimeout,
    open_port,
)
from maniskill_irb120.abb.emulator.controller import ControllerEmulator, run_pendant  # noqa: E402
from maniskill_irb120.abb.protocol import (  # noqa: E402
    JOINT_UNIT_RAD,
    ErrorCode,
    Frame,
    FrameParser,
    GetState,
    Hello,
    MsgType,
    ProtocolError,
    RobotState,
    Status,
    ToolStep,
    command_frame,
    decode_command,
    decode_reply,
)

STEP = ToolStep(0.006, 0.0, 0.0, 0.0)  # 6 mm along the tool's approach axis
STEP_MM = 6.0


class Wire:
    """A raw client on the emulator's URL (TCP or the serial pty): frames out, frames in."""

    def __init__(self, url: str):
        self.port = open_port(url, 0.05)
        self.parser = FrameParser()
        self.frames: list[Frame] = []

    def send(self, raw: bytes) -> None:
        self.port.write(raw)

    def reply(self, timeout: float = 1.0) -> Frame | None:
        """The next frame from the controller, or None if none came within ``timeout``."""
        end = time.monotonic() + timeout
        while not self.frames:
            left = end - time.monotonic()
            if left <= 0:
                return None
            self.port.timeout = min(left, 0.05)
            data = self.port.read(max(1, self.port.in_waiting))
            self.frames += self.parser.feed(data) if data else self.parser.expire()
        return self.frames.pop(0)

    def ask(self, msg, seq: int, timeout: float = 1.0, resend_s: float = 0.25) -> RobotState:
        """The decoded reply to ``msg``, resending the identical frame every ``resend_s`` as the client does;
        replies to other frames are skipped."""
        raw = command_frame(msg, seq).encode()
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            self.send(raw)
            until = time.monotonic() + min(resend_s, left)
            while (frame := self.reply(until - time.monotonic())) is not None:
                if frame.seq == seq and frame.type == MsgType.REPLY | msg.TYPE:
                    return decode_reply(frame)
        raise AssertionError(f"no reply to {msg} (seq {seq})")

    def close(self) -> None:
        self.port.close()


def wait_for(cond, timeout: float = 2.0) -> bool:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def tcp_mm(emu: ControllerEmulator) -> np.ndarray:
    return emu.robot.tool_pose(emu.robot.joints(), np.eye(4))[:3, 3] * 1000


def moved_mm(emu: ControllerEmulator, since: np.ndarray) -> float:
    return float(np.linalg.norm(tcp_mm(emu) - since))


def refusals(emu: ControllerEmulator) -> int:
    return sum(e.title == "IRB120Server: refused" for e in emu.events())


def watchdog_stops(emu: ControllerEmulator) -> list[float]:
    return [e.time for e in emu.events() if e.title == "IRB120Server: watchdog stop"]


@pytest.fixture
def make():
    """``make(channel, **kwargs)``: a started emulator (``.url``), stopped after the test, which checks the RAPID
    program met no error."""
    emus = []

    def start(channel: str = "tcp", **kwargs) -> ControllerEmulator:
        emu = ControllerEmulator(channel, **kwargs)
        emu.url = emu.start()
        emus.append(emu)
        return emu

    yield start
    for emu in emus:
        emu.stop()
        assert emu.error is None, emu.error


def halt(emu: ControllerEmulator, how: str) -> None:
    """The program halted by the pendant's Stop button or an emergency stop (then reset, the motors on)."""
    if how == "stop":
        emu.press_stop()
    else:
        emu.emergency_stop()
    assert wait_for(emu.interp.halted.is_set)
    if how == "estop":
        emu.reset_emergency_stop()
        emu.enabling_device(True)


# --------------------------------------------------------------------------- 1. a refused HELLO
@pytest.mark.parametrize(
    "hello, refused",
    [(Frame(MsgType.HELLO, 5, bytes([2])), ErrorCode.VERSION), (Frame(MsgType.HELLO, 5), ErrorCode.BAD_LENGTH)],
    ids=["version 2", "empty"],
)
def test_a_refused_hello_keeps_the_restart_hold(make, hello, refused):
    """Finding 1: after an emergency stop and Start without PP to main, a HELLO the server refuses (another
    version, no payload) lifted the restart hold and the next step moved the robot. Only an accepted HELLO opens a
    session; the refused one changes nothing."""
    emu = make("tcp")
    wire = Wire(emu.url)
    assert wire.ask(Hello(), 1).error == ErrorCode.OK
    halt(emu, "estop")
    emu.press_start()
    wire.send(hello.encode())
    assert decode_reply(wire.reply()).error == refused
    before = tcp_mm(emu)
    state = wire.ask(STEP, 6)
    assert state.error == ErrorCode.RESTARTED and state.status == Status.HELD
    time.sleep(0.2)
    assert emu.moves == 0 and moved_mm(emu, before) < 0.01
    assert wire.ask(Hello(), 7).error == ErrorCode.OK  # the accepted one lifts it
    assert wire.ask(STEP, 8).error == ErrorCode.OK and emu.moves == 1
    wire.close()


# --------------------------------------------------------------------------- 2. serial, PP to main
def test_a_step_sent_while_stopped_never_runs_after_pp_to_main_on_serial(make):
    """Finding 2: motors off, a TOOL_STEP sent while the program stood still, PP to main, Start: the step ran. The
    emulator's ClearIOBuff dropped only bytes it had already taken from the line; an IRC5's clears the device's
    input buffer, which the server's channel module does when it opens the line."""
    emu = make("serial")
    wire = Wire(emu.url)
    assert wire.ask(Hello(), 1).error == ErrorCode.OK
    emu.motors_off_fault("test")
    assert wait_for(emu.interp.halted.is_set)
    before = tcp_mm(emu)
    wire.send(command_frame(STEP, 2).encode())
    time.sleep(0.1)
    emu.pp_to_main()
    emu.enabling_device(True)
    emu.press_start()
    assert wire.reply(0.6) is None  # never answered
    assert emu.moves == 0 and moved_mm(emu, before) < 0.01
    assert wire.ask(STEP, 3).error == ErrorCode.OK and emu.moves == 1  # what the PC sends now is served
    wire.close()


# --------------------------------------------------------------------------- 3. a client that has gone
@pytest.mark.parametrize("served", ["closes", "falls silent"])
def test_a_step_from_a_client_that_has_gone_never_runs(make, served):
    """Finding 3: client B sent a TOOL_STEP while A was served, then closed; when A closed (or fell silent and was
    replaced) the server turned to B and ran the step. A client's bytes from before the server turned to it are
    dropped, and a client that has closed is passed over; the next client is served."""
    emu = make("tcp")
    a = Wire(emu.url)
    assert a.ask(GetState(), 1).error == ErrorCode.OK
    b = Wire(emu.url)
    b.send(command_frame(STEP, 1).encode())
    time.sleep(0.05)
    b.close()
    before = tcp_mm(emu)
    if served == "closes":
        a.close()
    time.sleep(2.0)  # A closed, or silent for SILENCE_S: the server has turned to B and found it gone
    assert emu.moves == 0 and moved_mm(emu, before) < 0.01
    c = Wire(emu.url)
    assert c.ask(STEP, 1, timeout=3.0).error == ErrorCode.OK and emu.moves == 1
    a.close()
    c.close()


def test_a_waiting_client_is_served_once_it_sends_again(make):
    """The other side of finding 3's rule: a live client whose frames came before the server turned to it is
    served when it resends (the client's connect resends its HELLO until answered)."""
    emu = make("tcp")
    a = Wire(emu.url)
    assert a.ask(GetState(), 1).error == ErrorCode.OK
    b = Wire(emu.url)
    b.send(command_frame(STEP, 1).encode())
    time.sleep(0.1)
    a.close()
    assert b.reply(0.5) is None and emu.moves == 0  # dropped: sent while A held the robot
    assert b.ask(STEP, 2).error == ErrorCode.OK and emu.moves == 1
    b.close()


# --------------------------------------------------------------------------- 4. the watchdog and a half frame
@pytest.mark.parametrize(
    "tail, after",
    [(b"", 0.0), (bytes([0xA5, 0x20, 0x01, 0x00]), 0.0), (bytes([0xA5, 0x20, 0x01, 0x00]), 0.4)],
    ids=["silence", "half a frame", "half a frame 0.4 s later"],
)
def test_a_half_sent_frame_does_not_delay_the_watchdog(make, tail, after):
    """Finding 4: a step, then the four bytes A5 20 01 00 and silence: the watchdog fired after 3.08 s instead of
    ~0.5 s (the header and the payload were each given their own frame time, 0.5 s + 50 ms a byte) and the robot
    went on 4.4 mm. A frame's rest must come within FRAME_S of its sync, and while the robot moves the wait for it
    ends when the watchdog is due, however late in the heartbeat the partial frame began."""
    emu = make("tcp", speed_scale=0.01)  # a 10 mm step takes seconds: the robot is still moving at 0.5 s
    stops = []  # when the server called StopMove
    stop_move = emu.interp.builtins.get("StopMove")
    stop_move.fn = (lambda fn: lambda *a, **k: (stops.append(time.monotonic()), fn(*a, **k))[1])(stop_move.fn)
    wire = Wire(emu.url)
    assert wire.ask(Hello(), 1).error == ErrorCode.OK
    assert wire.ask(ToolStep(0.01, 0.0, 0.0, 0.0), 2).status == Status.MOVING
    sent = time.monotonic()
    start = tcp_mm(emu)
    time.sleep(after)
    wire.send(tail)
    assert wait_for(lambda: watchdog_stops(emu), 4.0)
    assert stops[0] - sent < 0.5 + 0.2  # HEARTBEAT_S, and the time to read and act: the late one was 2.2-3.1 s
    assert wait_for(lambda: not emu.robot.busy())
    assert moved_mm(emu, start) < 1.0  # plain silence: ~0.3 mm; the late watchdog let it go 4.4-5.2 mm
    wire.close()


# --------------------------------------------------------------------------- 5. corrupted frames
CORRUPTIONS = {
    "truncated frame": command_frame(STEP, 9).encode()[:8],
    "length 32 header": bytes([0xA5, 0x20, 0x01, 0x00]),
    "length over 32": bytes([0xA5, 0x21, 0x01, 0x00]),
    "A5 FF": bytes([0xA5, 0xFF]),
    "lone sync": bytes([0xA5]),
    "bad CRC": command_frame(STEP, 9).encode()[:-1] + bytes([command_frame(STEP, 9).encode()[-1] ^ 0x55]),
}


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
def test_a_corrupted_frame_does_not_swallow_the_next(make, corruption):
    """Finding 5: each corruption, followed at once by a valid frame, lost the valid frame (the server read past
    the corrupted frame's end into it). The server's parser keeps every byte after a dropped sync and scans them
    again: the valid step behind it runs, once; an incomplete frame costs its frame time at most."""
    emu = make("tcp")
    wire = Wire(emu.url)
    assert wire.ask(Hello(), 1).error == ErrorCode.OK
    before = tcp_mm(emu)
    t0 = time.monotonic()
    wire.send(CORRUPTIONS[corruption] + command_frame(STEP, 2).encode())
    frame = wire.reply(3.0)
    took = time.monotonic() - t0
    assert frame is not None and frame.seq == 2 and frame.type == MsgType.REPLY | MsgType.TOOL_STEP
    assert decode_reply(frame).error == ErrorCode.OK and emu.moves == 1
    assert wait_for(lambda: not emu.robot.busy())
    assert abs(moved_mm(emu, before) - STEP_MM) < 0.1
    incomplete = corruption in ("truncated frame", "length 32 header")
    assert took < (0.5 + 0.3 if incomplete else 0.4)  # FRAME_S only for a frame that never completes
    wire.close()


@pytest.mark.parametrize("channel", ["serial", "tcp"])
def test_the_client_is_served_after_a_corrupted_header(make, channel):
    """Finding 5 through the client: after a 4-byte header claiming 32 bytes, hello() and the next state() both
    timed out (the server read the HELLO and its retries as the bogus frame's payload). The bogus frame is given
    up FRAME_S after its sync and the HELLO behind it is answered, within the client's three tries."""
    emu = make(channel)
    robot = ABBRobot.connect(emu.url)
    robot.port.write(bytes([0xA5, 0x20, 0x01, 0x00]))
    assert robot.hello().error == ErrorCode.OK
    assert robot.state().error == ErrorCode.OK
    robot.close()


# --------------------------------------------------------------------------- 6. the watchdog across sessions
def test_a_new_client_after_a_watchdog_stop_is_not_refused(make):
    """Finding 6: the old client fell silent mid-motion (the watchdog stopped the robot); the new client's first
    step after HELLO was refused WATCHDOG. A session start (a new connection, an accepted HELLO) clears it: the
    new client's HELLO reply already says HELD. The same session still gets its WATCHDOG refusal."""
    emu = make("tcp", speed_scale=0.01)
    old = ABBRobot.connect(emu.url, timeout=0.5)
    old.move_tool([1.0, 0.0, 0.0, 0.0, 1.0])
    assert wait_for(lambda: watchdog_stops(emu), 1.5)
    new = ABBRobot.connect(emu.url)
    assert new.last_state.status == Status.HELD
    assert new.move_tool([0.5, 0.0, 0.0, 0.0, 1.0]).error == ErrorCode.OK
    new.close()
    old.port.close()


def test_the_same_session_learns_of_a_watchdog_stop(make):
    emu = make("tcp", speed_scale=0.01)
    wire = Wire(emu.url)
    assert wire.ask(Hello(), 1).error == ErrorCode.OK
    assert wire.ask(STEP, 2).error == ErrorCode.OK
    assert wait_for(lambda: watchdog_stops(emu), 1.5)
    assert wire.ask(STEP, 3).error == ErrorCode.WATCHDOG
    assert wire.ask(STEP, 4).error == ErrorCode.OK
    wire.close()


# --------------------------------------------------------------------------- 7. connect waits
def test_the_default_connect_waits_out_a_silent_client(make, caplog):
    """Finding 7: with a silent connection open, connect with its defaults gave up after 1.05 s; the server turns
    to a new client about 1.5 s after it connects. connect resends its HELLO for CONNECT_WAIT_S and logs what it
    is waiting for."""
    emu = make("tcp")
    silent = Wire(emu.url)
    assert silent.ask(GetState(), 1).error == ErrorCode.OK
    t0 = time.monotonic()
    with caplog.at_level("INFO", logger="maniskill_irb120.abb.client"):
        robot = ABBRobot.connect(emu.url)
    assert 0.9 < time.monotonic() - t0 < CONNECT_WAIT_S
    assert "waiting up to 2.5 s for the controller to turn to this connection" in caplog.text
    assert robot.state().error == ErrorCode.OK
    robot.close()
    silent.close()


def test_connect_says_what_it_waited_for(make):
    """A client that keeps sending is never replaced: connect gives up after CONNECT_WAIT_S and says why."""
    emu = make("tcp")
    busy = Wire(emu.url)
    assert busy.ask(GetState(), 1).error == ErrorCode.OK
    done = threading.Event()

    def keep_sending() -> None:
        seq = 2
        while not done.is_set():
            busy.send(command_frame(GetState(), seq).encode())
            seq = seq % 255 + 1
            time.sleep(0.1)

    sender = threading.Thread(target=keep_sending, daemon=True)
    sender.start()
    t0 = time.monotonic()
    with pytest.raises(RobotTimeout, match="serves one client at a time"):
        ABBRobot.connect(emu.url)
    assert CONNECT_WAIT_S - 0.1 < time.monotonic() - t0 < CONNECT_WAIT_S + 1.0
    done.set()
    sender.join()
    busy.close()
    with pytest.raises(ValueError, match="wait=-1"):
        ABBRobot.connect(emu.url, wait=-1)


# --------------------------------------------------------------------------- 8. moving again after PP to main
@pytest.mark.parametrize("how", ["stop", "estop"])
@pytest.mark.parametrize("channel", ["serial", "tcp"])
def test_the_robot_moves_again_after_pp_to_main(make, channel, how):
    """Finding 8: after the Stop button or an emergency stop, PP to main and Start, a fresh client's first step was
    answered OK and moved 0.00 mm, and the next got no reply: the emulator kept the halt's stop on the path. A
    program started from main moves the robot: both steps run, 6 mm each."""
    emu = make(channel)
    robot = ABBRobot.connect(emu.url, timeout=0.5)
    robot.move_tool([0.6, 0.0, 0.0, 0.0, 1.0])
    halt(emu, how)
    emu.pp_to_main()
    emu.press_start()
    robot.port.close()
    again = ABBRobot.connect(emu.url, timeout=0.5)
    for _ in range(2):
        before = tcp_mm(emu)
        assert again.move_tool([0.6, 0.0, 0.0, 0.0, 1.0]).error == ErrorCode.OK
        assert wait_for(lambda: not emu.robot.busy())
        assert abs(moved_mm(emu, before) - STEP_MM) < 0.1
    again.close()


# --------------------------------------------------------------------------- smaller findings
def test_a_repeated_refusal_is_logged_once(make):
    """A refused step repeated with a STATE between the tries logged a "refused" event every time (30 in 30). Each
    kind of refusal is logged once until a command other than STATE is accepted."""
    emu = make("tcp")
    wire = Wire(emu.url)
    seq = 1
    for _ in range(10):
        assert wire.ask(ToolStep(0.02, 0.0, 0.0, 0.0), seq).error == ErrorCode.STEP_LIMIT
        assert wire.ask(GetState(), seq + 1).error == ErrorCode.OK
        seq += 2
    assert refusals(emu) == 1
    assert wire.ask(STEP, seq).error == ErrorCode.OK  # accepted: the next refusal is news again
    assert wire.ask(ToolStep(0.02, 0.0, 0.0, 0.0), seq + 1).error == ErrorCode.STEP_LIMIT
    assert refusals(emu) == 2
    wire.close()


def gripper_frames(emu: ControllerEmulator) -> dict[str, Frame]:
    here = [round(np.radians(q) / JOINT_UNIT_RAD) for q in emu.robot.joints()]
    return {
        "tool step, byte 3": Frame(MsgType.TOOL_STEP, 3, struct.pack("<4hB", 0, 0, 0, 0, 3)),
        "joints, byte 255": Frame(MsgType.JOINTS, 3, struct.pack("<6hB", *here, 255)),
        "gripper, byte 2": Frame(MsgType.GRIPPER, 3, bytes([2])),
    }


@pytest.mark.parametrize("which", ["tool step, byte 3", "joints, byte 255", "gripper, byte 2"])
def test_a_gripper_byte_the_protocol_does_not_define_is_refused_on_both_sides(make, which):
    """Gripper bytes 3..255 were "close" in RAPID while the PC's parser refused them. Both sides refuse them now:
    the server with BAD_VALUE (nothing moves, the gripper stays open), the parser with a ProtocolError."""
    emu = make("tcp")
    frame = gripper_frames(emu)[which]
    with pytest.raises(ProtocolError, match="gripper byte"):
        decode_command(frame)
    wire = Wire(emu.url)
    wire.send(frame.encode())
    state = decode_reply(wire.reply())
    assert state.error == ErrorCode.BAD_VALUE and "gripper byte" in state.meaning
    time.sleep(0.1)
    assert emu.moves == 0 and emu.signals["doGripperOpen"] == 1
    assert wire.ask(GetState(), 4).gripper_open
    wire.close()


# --------------------------------------------------------------------------- the pendant from a script
def test_pendant_commands_say_what_the_controller_did(make):
    """The emulator's pendant as commands (``maniskill-irb120 emulator --pendant -``): each prints the program's
    state after it, a refusal says why, and a command that does not exist is named with the ones that do; the
    script goes on after a bad line."""
    emu = make("tcp")
    out = io.StringIO()
    run_pendant(emu, ["estop; start", "reset-estop", "motors-on; pp-to-main # the operator's restart", "start", "jump"])
    run_pendant(emu, ["wait -1", "state", "quit", "stop"], out)
    lines = out.getvalue().splitlines()
    assert lines[0] == "pendant: error: pendant command 'wait -1': wait takes a time in seconds >= 0"
    assert lines[1] == "pendant: state: program running, motors on, emergency stop off, key manual_reduced"
    assert lines[2] == "pendant: quit" and len(lines) == 3  # nothing after quit
    out = io.StringIO()
    run_pendant(emu, ["estop", "start", "dance"], out)
    lines = out.getvalue().splitlines()
    assert lines[0] == "pendant: estop: program stopped, motors off, emergency stop active, key manual_reduced"
    assert lines[1].startswith("pendant: start: refused: emergency stop active")
    assert lines[2].startswith("pendant: error: pendant command 'dance': use one of stop, start, pp-to-main")


def test_a_fault_and_restart_scripted_out_of_process(tmp_path):
    """An integrator's harness: the emulator in its own process, its pendant on stdin. An emergency stop silences
    the controller (the client says to check the pendant); reset, motors on, PP to main and Start, and a new client
    is served and moves the robot."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "maniskill_irb120", "emulator", "--listen", "tcp://127.0.0.1:0", "--pendant", "-"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        bufsize=1,
    )

    def pendant(command: str) -> str:
        proc.stdin.write(command + "\n")
        proc.stdin.flush()
        return proc.stdout.readline().strip()

    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("tcp://127.0.0.1:")
        robot = ABBRobot.connect(url, timeout=0.3, retries=1)
        robot.move_tool([0.6, 0.0, 0.0, 0.0, 1.0])
        assert pendant("estop").startswith("pendant: estop: program stopped, motors off")
        with pytest.raises(ControllerStopped, match="check the pendant"):
            robot.move_tool([0.6, 0.0, 0.0, 0.0, 1.0])
        robot.port.close()
        for command in ("reset-estop", "motors-on", "pp-to-main"):
            assert pendant(command).startswith(f"pendant: {command}: program stopped")
        assert pendant("start") == "pendant: start: program running, motors on, emergency stop off, key manual_reduced"
        again = ABBRobot.connect(url)
        held = again.last_state  # the HELLO's reply: where the robot stands, held
        state = again.move_tool([0.6, 0.0, 0.0, 0.0, 1.0])
        assert state.error == ErrorCode.OK and held.status == Status.IDLE
        moved = np.linalg.norm(np.subtract(state.target_pos, held.target_pos)) * 1000
        assert abs(moved - STEP_MM) < 0.1
        again.close()
        assert pendant("quit") == "pendant: quit"
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait()


def test_cli_pendant_takes_stdin_or_a_file(tmp_path, capsys):
    from maniskill_irb120.cli import main

    assert main(["emulator", "--pendant", str(tmp_path / "missing.txt")]) == 2
    assert "--pendant" in capsys.readouterr().err
    script = tmp_path / "restart.txt"
    script.write_text("stop  # the Stop button\nstate; quit\n")
    assert main(["emulator", "--pendant", str(script)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("tcp://127.0.0.1:")
    assert out[1:] == [
        "pendant: stop: program stopped, motors on, emergency stop off, key manual_reduced",
        "pendant: state: program stopped, motors on, emergency stop off, key manual_reduced",
        "pendant: quit",
    ]


def test_a_payload_with_an_equal_crc_is_answered_from_the_cache_and_moves_nothing(make):
    """The cache trusts the CRC-16 (docs/protocol.md): a different payload under the same number and type with an
    equal CRC is answered from the cache, not executed. Crafted: XOR-ing the generator polynomial 0x11021 into the
    payload leaves the CRC as it is (the CRC is linear); here dz changes by 2.56 mm and the turn by 8.464 deg."""
    emu = make("tcp")
    first = command_frame(STEP, 7).encode()
    body = bytearray(first[1:-2])
    for i, d in zip(range(8, 12), (0x01, 0x10, 0x21, 0x00)):  # dz high byte, turn low and high byte, gripper
        body[i] ^= d
    crafted = first[:1] + bytes(body) + first[-2:]
    assert crafted != first and decode_command(FrameParser().feed(crafted)[0]) != STEP  # a valid, other step
    wire = Wire(emu.url)
    wire.send(first)
    executed = wire.reply()
    wire.send(crafted)
    assert wire.reply() == executed  # the cached reply
    time.sleep(0.1)
    assert emu.moves == 1
    wire.close()

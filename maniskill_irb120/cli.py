"""``maniskill-irb120``: the package's one command line (tyro subcommands, as ManiSkill's own scripts use
tyro). ``python -m maniskill_irb120`` forwards here."""

from __future__ import annotations

import functools
import inspect
import io
import ipaddress
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import tyro

from maniskill_irb120.envs.table_clearing import ENV_ID as DEFAULT_ENV_ID
from maniskill_irb120.errors import (
    UsageError,
    check_count,
    nearest,
    say_usage_error,
    terminate_as_interrupt,
    tyro_error_line,
)


def doctor(json: bool = False, gpu: bool = False, json_path: str | None = None, jobs: int = 1) -> int:
    """Check the Vulkan/render device, CUDA sim support and package versions (exit 1 if rendering fails).
    ``--gpu``: run the GPU acceptance suite instead (every task and obs mode at 512 envs on physx_cuda, partial
    resets, controller targets, contacts against the CPU, batched RGB-D, steps/s at 512/1024/4096 envs) and print
    one report to paste into an issue (exit 1 if a check fails, 2 without CUDA; takes a few minutes). The
    trainers' and the benchmark's tiny GPU runs are programs of a source checkout, not of this package: there,
    ``python -m benchmarks.gpu_acceptance`` (same flags) prints this report with them added. ``--jobs N``: N
    checks side by side, each in its own process (the obs-mode sweep split per task and mode); the steps/s are
    timed afterwards, alone. ``--json``: print the report as JSON; ``--json-path PATH``: also write it there.

    Args:
        json: print the report as JSON
        gpu: run the GPU acceptance suite (needs CUDA; a few minutes)
        json_path: also write the report to this file
        jobs: with --gpu, how many checks run side by side, each in its own process
    """
    from maniskill_irb120.diagnostics.doctor import gpu_main, main

    check_count("--jobs", jobs)
    if gpu:
        return gpu_main(json_output=json, json_path=json_path, jobs=jobs)
    return main(json_output=json, json_path=json_path)


def collect_demos(
    env_id: str = DEFAULT_ENV_ID,
    episodes: int = 10,
    seed: int = 0,
    out_dir: str = "demos",
    name: str = "expert",
    obs_mode: str = "none",
    keep_failures: bool = False,
    save_video: bool = False,
    object_shape: str = "cube",
    control_mode: str = "pd_ee_delta_tool",
) -> int:
    """Record scripted-expert episodes of a task in ManiSkill's trajectory format (h5 + json). ``--control-mode
    pd_joint_pos`` records the joint targets the expert's tool actions command, which ManiSkill's replay tool
    converts to its other modes (``-c pd_joint_delta_pos``, ``-c pd_ee_delta_pose``).

    Args:
        env_id: the task (TableClearing-, GraspLift- or StackCube-IRB120-v1)
        episodes: how many episodes to run, seeds seed..seed+episodes-1
        seed: the first episode's seed
        out_dir: where NAME.h5 and NAME.json go
        name: the trajectory files' name
        obs_mode: the observations recorded (none: replay them later with ManiSkill's tool)
        keep_failures: keep the episodes the expert failed too
        save_video: write an mp4 per episode beside the trajectories
        object_shape: cube, cylinder or random (redrawn every episode)
        control_mode: what is recorded: pd_ee_delta_tool (the tool actions) or pd_joint_pos (the joint targets)
    """
    check_count("--episodes", episodes)
    _check_env_id(env_id)
    from maniskill_irb120.experts.demos import collect_demos as collect

    print(
        json.dumps(
            collect(
                episodes,
                seed,
                Path(out_dir),
                name,
                obs_mode,
                not keep_failures,
                save_video,
                env_id=env_id,
                control_mode=control_mode,
                object_shape=object_shape,
            )
        )
    )
    return 0


def expert(
    env_id: str = DEFAULT_ENV_ID,
    episodes: int = 100,
    seed: int = 0,
    obs_mode: str = "state",
    object_shape: str = "cube",
    reactive: bool = False,
) -> int:
    """Run a task's scripted expert on seeds seed..seed+episodes-1; print one JSON line (success_rate,
    episodes, mean_steps, failures, ...). ``object_shape="random"`` redraws the shape every episode.
    ``--reactive``: the expert reads its phase from the state each step (the one DAgger relabels with).

    Args:
        env_id: the task (TableClearing-, GraspLift- or StackCube-IRB120-v1)
        episodes: how many episodes to run
        seed: the first episode's seed
        obs_mode: the env's observations (the expert reads the state either way)
        object_shape: cube, cylinder or random (redrawn every episode)
        reactive: the expert reads its phase from the state each step
    """
    check_count("--episodes", episodes)
    _check_env_id(env_id)
    from maniskill_irb120.experts.rollout import run_expert

    kwargs = dict(reconfiguration_freq=1) if object_shape == "random" else {}
    print(
        json.dumps(
            run_expert(
                env_id, episodes, seed, obs_mode=obs_mode, reactive=reactive, object_shape=object_shape, **kwargs
            )
        )
    )
    return 0


def emulator(
    listen: str = "tcp://127.0.0.1:0",
    rapid: str | None = None,
    fault: str | None = None,
    latency_ms: float = 0.0,
    speed_scale: float = 1.0,
    options: str | None = None,
    op_mode: str = "manual_reduced",
    statement_cost_us: float = 10.0,
    pc_address: str | None = None,
    rws: str | None = None,
    pendant: str | None = None,
    operator: str = "grant",
    max_sessions: int = 70,
    session_idle_s: float = 900.0,
) -> int:
    """Run the ABB controller emulator: the RAPID server module on an emulated IRB 120, served on TCP or a serial
    pty, or (``--rws``) a controller serving Robot Web Services, what ``deploy`` talks to. Prints the URL to connect
    to as its first line; Ctrl-C stops it. A module that names anything of a missing RobotWare option is refused as
    the IRC5 refuses it: the load error is printed and the exit status is 1. Faults (``--fault``): drop, corrupt,
    dup, delay@N:MS, disconnect, motors_off, estop. Pendant controls (``--pendant``), one or more a line separated by
    ``;``: stop, start, pp-to-main, estop, reset-estop, motors-off, motors-on, wait SECONDS, state, quit; each prints a
    ``pendant: ...`` line with the program's state, so a fault and the operator's restart can be scripted.

    Args:
        listen: where to serve: tcp://127.0.0.1:PORT (0: a free port), serial://pty or serial://pty?baudrate=9600
        rapid: another copy of the RAPID server module to run (None: the package's)
        fault: faults in the N-th reply, e.g. "drop@2,delay@3:300": drop, corrupt, dup, delay@N:MS, disconnect, ...
        latency_ms: hold every command back this many ms before the controller sees it
        speed_scale: 0.8 makes every motion take 1/0.8 of its time
        options: the RobotWare options the controller has, e.g. "616-1,608-1" ("" for none)
        op_mode: the key switch OpMode() reads: manual_reduced, auto or manual_full (auto moves only if ALLOW_AUTO)
        statement_cost_us: controller time one RAPID statement costs, in us (an estimate; 0: no pacing)
        pc_address: the TCP build's PC_ADDRESS, the one client address served (None: 127.0.0.1)
        rws: serve Robot Web Services 1.0 on 127.0.0.1:PORT instead, the stock MainModule loaded
        pendant: FlexPendant controls from stdin (-) or a file, e.g. "stop; wait 2; start" (not with --rws)
        operator: with --rws, the person at the pendant answering a remote RMMP request: grant, deny or absent
        max_sessions: with --rws, how many RWS sessions the controller keeps (RobotWare 6: 70 assumed)
        session_idle_s: with --rws, how long an unused RWS session lasts, in s (RobotWare 6: 900 assumed)
    """
    from maniskill_irb120.abb.emulator.controller import OP_MODE_NAMES
    from maniskill_irb120.abb.emulator.controller import main as emulator_main
    from maniskill_irb120.abb.emulator.rapid import parse_options

    if options is not None:
        try:
            parse_options(options)
        except ValueError as e:
            print(f"--options: {e}", file=sys.stderr)
            return 2
    if op_mode not in OP_MODE_NAMES:
        print(f"--op-mode {op_mode!r}: use one of {sorted(OP_MODE_NAMES)}", file=sys.stderr)
        return 2
    if not (math.isfinite(statement_cost_us) and statement_cost_us >= 0):
        print(f"--statement-cost-us {statement_cost_us!r}: a time >= 0 us per statement (0: off)", file=sys.stderr)
        return 2
    if operator not in ("grant", "deny", "absent"):
        print(f"--operator {operator!r}: grant, deny or absent", file=sys.stderr)
        return 2
    if rws is not None and pendant is not None:
        print(
            "--pendant drives the program --listen serves; with --rws the program is started over RWS", file=sys.stderr
        )
        return 2
    if rws is not None:
        from maniskill_irb120.abb.emulator.rws import main as rws_main

        try:
            return rws_main(
                rws,
                options,
                op_mode,
                statement_cost_us,
                operator=operator,
                max_sessions=max_sessions,
                session_idle_s=session_idle_s,
            )
        except ValueError as e:
            print(e, file=sys.stderr)
            return 2
    if pc_address is not None:
        if not listen.startswith("tcp:"):
            print("--pc-address: only the TCP build serves a PC address (--listen tcp://...)", file=sys.stderr)
            return 2
        try:
            ipaddress.IPv4Address(pc_address)
        except ValueError:
            print(f"--pc-address {pc_address!r}: an IPv4 address, e.g. 192.168.125.2", file=sys.stderr)
            return 2
    if pendant is not None and pendant != "-" and not Path(pendant).is_file():
        print(f"--pendant {pendant!r}: '-' (stdin) or a file of pendant commands", file=sys.stderr)
        return 2
    return emulator_main(
        listen, rapid, fault, latency_ms, speed_scale, options, op_mode, statement_cost_us, pc_address, pendant
    )


def deploy(
    action: tyro.conf.Positional[Literal["load", "status", "start", "stop", "unload"]] = "load",
    controller: str | None = None,
    user: str = "Default User",
    password: str = "robotics",
    yes: bool = False,
    channel: str = "auto",
    zone: str = "auto",
    rapid_dir: str | None = None,
    events: int = 5,
    rmmp_wait: float = 60.0,
    mastership_wait: float = 60.0,
) -> int:
    """Deploy the RAPID server to an IRC5 (RobotWare 6) over Robot Web Services. ``load`` reads the RobotWare
    version, options, operating mode and controller state, picks the files the option matrix allows (serial: no
    option; TCP: 616-1 or 672-1; the world zone: 608-1) and says why, then as one transaction takes remote access
    and mastership, uploads to a new folder under $HOME/IRB120, loads into T_ROB1, reads the modules back and,
    after you confirm, sets PP at IRB120Server with the program stopped; on any failure or Ctrl-C the earlier
    deployment is put back. ``status``: the execution state, operating mode, controller state, speed ratio and the
    last ``--events`` events; ``unload``: our modules and the files deploy wrote (PP to main if ours held it). Needs
    the ``real`` extra (abb-robot-client). Exit status 1 when refused, 2 on bad flags.

    Args:
        action: load (the transaction above), status, start (AUTO only, if ALLOW_AUTO), stop or unload
        controller: the IRC5's address, e.g. http://192.168.125.1 (needed)
        user: the RWS user (RWS's default)
        password: the RWS password (RWS's default)
        yes: confirm without asking (for scripts)
        channel: which build to load: auto, serial or tcp (refused naming a missing option)
        zone: the world-zone build: auto, on or off (on needs option 608-1)
        rapid_dir: a folder with your edited copies of the RAPID files (SER_CHANNEL, PC_ADDRESS, ...)
        events: how many of the controller's last events status prints
        rmmp_wait: seconds the operator has to grant remote access on the FlexPendant (manual modes)
        mastership_wait: seconds to wait while another client holds mastership
    """
    from maniskill_irb120.abb import deploy as dep

    if controller is None:
        print("deploy: --controller http://HOST is required (the IRC5's address)", file=sys.stderr)
        return 2
    if channel not in ("auto", "serial", "tcp") or zone not in ("auto", "on", "off"):
        print("deploy: --channel auto|serial|tcp, --zone auto|on|off", file=sys.stderr)
        return 2
    if not (rmmp_wait >= 0 and mastership_wait >= 0):  # also NaN
        print("deploy: --rmmp-wait and --mastership-wait are seconds, 0 or more", file=sys.stderr)
        return 2
    waits = {"rmmp_wait_s": rmmp_wait, "mastership_wait_s": mastership_wait}
    say = lambda m: print(m, flush=True)  # noqa: E731

    def confirm(question: str) -> bool:
        if yes:
            say(f"{question} yes (--yes)")
            return True
        if not sys.stdin.isatty():
            say(f"{question} not confirmed: no terminal to answer at (pass --yes in scripts)")
            return False
        try:
            return input(f"{question} [y/N] ").strip().lower() in ("y", "yes")
        except EOFError:
            return False

    try:
        c = dep.connect(controller, user, password)
        try:
            if action == "load":
                dep.deploy(c, say, confirm, channel, zone, Path(rapid_dir) if rapid_dir else None, **waits)
            elif action == "status":
                dep.status(c, say, events)
            elif action == "start":
                dep.start(c, say, confirm)
            elif action == "stop":
                dep.stop(c, say)
            else:
                dep.unload(c, say, **waits)
        finally:
            c.close()  # logs out: the session's mastership and remote access end with it
    except dep.DeployRefused as e:
        print(f"deploy {action}: refused: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outside the transaction, which rolls back and says so itself
        print(f"deploy {action}: interrupted (Ctrl-C); deploy status shows what the controller holds", file=sys.stderr)
        return 130
    except Exception as e:  # the controller answered with an error, or did not answer
        print(f"deploy {action}: {dep._explain(e, 'the controller')}", file=sys.stderr)
        return 1
    return 0


def sim2real_eval(
    robot: str = "emulator",
    policy: str = "expert",
    actions: str = "as-trained",
    episodes: int = 10,
    seed: int = 1000,
    shift: str | None = None,
    sim_shift: bool = False,
    env_id: str = DEFAULT_ENV_ID,
    camera: str = "twin",
    camera_mount: str | None = None,
    command_mode: str = "tool_delta",
    step_end: str = "arrived",
    out: str = "runs/sim2real",
    operator_timeout_s: float = 60.0,
) -> int:
    """Run a policy on the same seeds in simulation and through the ABB adapter and measure the gap: writes
    OUT/report.json, OUT/report.md (+ pictures) and OUT/logs/ (what ``sysid`` fits). ``--robot emulator``: our
    RAPID module on the emulator with a digital twin as the world (``--shift "camera_fov=80,latency=0.02"``
    makes it differ from the sim; ``--sim-shift`` puts the sim in the same condition, its own prediction of it);
    ``--robot tcp://HOST:PORT`` or ``serial:///dev/ttyUSB0?baudrate=N``: a real
    IRC5 (``--camera realsense``; the operator scores each episode). ``--policy``: expert, an agents.ppo,
    agents.dagger or agents.sac checkpoint, or a committed policy's name in benchmarks/results/policies/MANIFEST.json
    (``camera-dr-mount-nolat``). ``--camera-mount "camera_pos=X;Y;Z,camera_rot=A;B;C"``: the camera's
    mount as hand-eye calibration measured it; frames are reprojected to the trained mount. ``--actions``: a
    checkpoint's action as its trainer evaluated it (as-trained), its mean, or a sample (agents.sac/agents.ppo;
    seeded by the episode seed on both sides). ``--step-end``: a real step ends when the robot stands at its target
    (arrived: what the sim's settled drives show; command latency then costs time only, and ``--sim-shift`` leaves
    it out of the sim side) or after one fixed 50 ms period (period: the robot still moving when read).
    Prints one JSON line; Ctrl-C or SIGTERM stops the robot and still writes the report.

    Args:
        robot: emulator, emulator+serial, tcp://HOST:PORT or serial:///dev/ttyUSB0?baudrate=N
        policy: expert, a checkpoint file, or a policy's name in benchmarks/results/policies/MANIFEST.json
        actions: a checkpoint's action: as-trained, mean or sample
        episodes: how many episodes, each on both sides
        seed: the first episode's seed (episode k runs seed + k on both sides)
        shift: how the twin's world differs from the sim, e.g. "camera_fov=80,latency=0.02"
        sim_shift: put the sim side in the --shift's condition too
        env_id: the task (TableClearing-, GraspLift- or StackCube-IRB120-v1)
        camera: twin (emulator only), realsense or none
        camera_mount: the camera's measured mount, e.g. "camera_pos=X;Y;Z,camera_rot=A;B;C"
        command_mode: tool_delta (RelTool on the controller) or joint_target (sim IK, MoveAbsJ)
        step_end: arrived (a real step ends at the target) or period (after one 50 ms period)
        out: where report.json, report.md and logs/ go
        operator_timeout_s: real robot: seconds to answer 'delivered? [y/n]' after each episode
    """
    check_count("--episodes", episodes)
    _check_env_id(env_id)
    from maniskill_irb120.sim2real.eval import EvalConfig
    from maniskill_irb120.sim2real.eval import main as eval_main

    cfg = EvalConfig(
        robot=robot,
        policy=policy,
        actions=actions,
        episodes=episodes,
        seed=seed,
        shift=shift,
        sim_shift=sim_shift,
        env_id=env_id,
        camera=camera,
        camera_mount=camera_mount,
        command_mode=command_mode,
        step_end=step_end,
        out=Path(out),
        operator_timeout_s=operator_timeout_s,
    )
    with terminate_as_interrupt():  # a SIGTERM (a scheduler's stop, a session's end) stops the robot as Ctrl-C does
        return eval_main(cfg)


def export_policy(checkpoint: str, out: str, command: str) -> int:
    """Write a trainer checkpoint's policy section alone (no optimiser or replay state: small enough to commit)
    to OUT, with the COMMAND that trained it; ``sim2real-eval --policy OUT`` and the benchmarks read it as they
    read the checkpoint. Prints one JSON line (its size, kind, task).

    Args:
        checkpoint: the trainer's checkpoint file
        out: where the policy section goes
        command: the command that trained the checkpoint (kept in the file)
    """
    from maniskill_irb120.policies.section import export_policy as export

    print(json.dumps(export(Path(checkpoint), Path(out), command)))  # a bad checkpoint or command: UsageError
    return 0


def sysid(log: str) -> int:
    """Fit the robot's command latency and speed scaling to a sim2real-eval run's logs (LOG/logs/real_*.npz):
    prints one JSON line (latency_s, speed_scale, RMS joint error of the fit and of the nominal robot) and
    writes LOG/sysid.json.

    Args:
        log: a sim2real-eval run's --out folder
    """
    from maniskill_irb120.sim2real.sysid import main as sysid_main

    sysid_main(log)
    return 0


def teleop(
    env_id: str = DEFAULT_ENV_ID,
    device: str = "keyboard",
    frame: str = "world",
    control_mode: str = "pd_ee_delta_tool",
    out_dir: str = "demos",
    name: str = "teleop",
    seed: int = 0,
    speed: float = 0.5,
    max_episode_steps: int = 1200,
    view: str = "auto",
    robot: str | None = None,
    step_mm: float = 2.0,
    step_deg: float = 1.0,
) -> int:
    """Drive a task by hand and record the saved episodes as ManiSkill trajectories (OUT_DIR/NAME.h5 + .json),
    or, with ``--robot``, jog a robot. ``--device keyboard`` (this terminal; works over SSH), ``spacemouse``
    (hidapi) or ``gamepad`` (/dev/input/js0); keys: w/s a/d r/f move along x/y/z, z/x turn, space toggles the
    gripper, Enter saves, Backspace resets, n discards, q quits. ``--frame world|tool``: the axes x/y/z move along.
    ``--control-mode pd_joint_pos`` records the joint targets, which ManiSkill's replay tool converts to its other
    modes. ``--robot emulator`` (our RAPID server on the controller emulator) or ``tcp://HOST:PORT`` /
    ``serial:///dev/ttyUSB0?baudrate=N`` (an IRC5): hold-to-run jogging at ``--step-mm`` / ``--step-deg`` per
    50 ms period, every step through the safety envelope. Prints one JSON line at the end.

    Args:
        env_id: the task (TableClearing-, GraspLift- or StackCube-IRB120-v1)
        device: keyboard, spacemouse or gamepad
        frame: the axes x/y/z move along: world or tool
        control_mode: what is recorded: pd_ee_delta_tool or pd_joint_pos
        out_dir: where NAME.h5 and NAME.json go
        name: the trajectory files' name
        seed: the first episode's seed
        speed: the share of the action's full step a full deflection commands, in (0, 1]
        max_episode_steps: an episode's time limit in steps
        view: auto, window or none: the overview and hand camera in a window
        robot: jog this robot instead: emulator, tcp://HOST:PORT or serial:///dev/ttyUSB0?baudrate=N
        step_mm: jogging: millimetres a 50 ms period at full deflection
        step_deg: jogging: degrees a 50 ms period at full deflection
    """
    from maniskill_irb120.teleop.devices import Merged, open_device

    check_count("--max-episode-steps", max_episode_steps)
    if robot is None:
        _check_env_id(env_id)
    try:
        dev = open_device(device)
    except (ValueError, RuntimeError) as e:  # no such device, not plugged in, not a terminal
        print(f"--device {device}: {e}", file=sys.stderr)
        return 2
    if device != "keyboard" and sys.stdin.isatty():
        dev = Merged(dev, open_device("keyboard"))  # save / discard / quit from the terminal too
    try:
        if robot is not None:
            return _jog(robot, dev, frame, step_mm, step_deg)
        from maniskill_irb120.teleop.keyboard import HELP
        from maniskill_irb120.teleop.sim import TeleopConfig
        from maniskill_irb120.teleop.sim import teleop as run

        cfg = TeleopConfig(
            env_id=env_id,
            frame=frame,
            control_mode=control_mode,
            out_dir=Path(out_dir),
            name=name,
            seed=seed,
            speed=speed,
            max_episode_steps=max_episode_steps,
            view=view,
        )
        print(HELP, flush=True)
        print(json.dumps(run(cfg, dev, say=lambda m: print(m, flush=True))))
        return 0
    finally:
        dev.close()


def _jog(robot: str, dev, frame: str, step_mm: float, step_deg: float) -> int:
    from maniskill_irb120.abb.client import ABBRobot
    from maniskill_irb120.teleop.jog import JogConfig, Jogger
    from maniskill_irb120.teleop.keyboard import HELP

    cfg = JogConfig(frame=frame, step_mm=step_mm, step_deg=step_deg)
    emu = None
    if robot == "emulator":
        from maniskill_irb120.abb.emulator.controller import ControllerEmulator

        emu = ControllerEmulator("tcp")
        robot = emu.start()
    try:
        with ABBRobot.connect(robot) as arm:
            print(f"{HELP}\nready: jogging {robot}, {frame} frame, {step_mm} mm / {step_deg} deg a period", flush=True)
            result = Jogger(arm, dev, cfg, say=lambda m: print(m, flush=True)).run()
        print(json.dumps(dict(robot=robot, **result)))
    finally:
        if emu is not None:
            emu.stop()
    return 0


def _check_env_id(env_id: str) -> None:
    """A wrong ``--env-id`` refused before anything is built, naming the package's tasks and the nearest one."""
    from maniskill_irb120.envs import check_env_id

    check_env_id(env_id)


PROG = "maniskill-irb120"

COMMANDS = {
    "doctor": doctor,
    "export-policy": export_policy,
    "collect-demos": collect_demos,
    "expert": expert,
    "emulator": emulator,
    "deploy": deploy,
    "sim2real-eval": sim2real_eval,
    "sysid": sysid,
    "teleop": teleop,
}


SUMMARY = {
    "doctor": "check rendering, CUDA and versions (--gpu: GPU acceptance)",
    "export-policy": "write a checkpoint's policy alone, small enough to commit",
    "collect-demos": "record scripted-expert episodes as ManiSkill trajectories",
    "expert": "run a task's scripted expert; print its success rate",
    "emulator": "run the ABB controller emulator with the RAPID server (or RWS)",
    "deploy": "deploy the RAPID server to an IRC5 over Robot Web Services",
    "sim2real-eval": "run a policy in the sim and on a robot; measure the gap",
    "sysid": "fit latency and speed scaling to a sim2real-eval run's logs",
    "teleop": "drive a task by hand and record episodes, or jog a robot",
}
"""one line per subcommand, for the top-level --help (each subcommand's own --help has its docstring); short enough
that every line of that help fits 80 columns"""


def _plain(doc: str | None) -> str:
    """A docstring as a terminal shows it: its text before the ``Args:`` section (tyro turns those into the flags'
    help), with RST's ``literal`` marks taken off."""
    text = inspect.cleandoc(doc or "").split("\nArgs:\n")[0].strip()
    return re.sub(r"``(.+?)``", r"\1", text, flags=re.S)


def _usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f"  {name:<{width}}  {SUMMARY[name]}" for name in COMMANDS]
    return "\n".join(
        [
            f"usage: {PROG} COMMAND [FLAGS]",
            "",
            "The ABB IRB 120 on ManiSkill 3: experts, demos, sim-to-real and the robot side.",
            f"{PROG} COMMAND --help: a command's flags.",
            "",
            "commands:",
            *lines,
        ]
    )


def _parsed(fn, stderr, held: io.StringIO):
    """``fn`` for tyro to call once it has parsed the flags: ``stderr`` is given back first, with anything tyro wrote
    to it meanwhile."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        sys.stderr = stderr
        stderr.write(held.getvalue())
        return fn(*args, **kwargs)

    return call


def main(argv: list[str] | None = None) -> int:
    """Run the subcommand ``argv`` names. A :class:`~maniskill_irb120.errors.UsageError` (a wrong env id, a missing
    or unreadable file, a count below 1) is printed as one line and exits with status 2, as tyro's own flag errors
    do; anything else keeps its traceback."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv in ([], ["-h"], ["--help"]):
        print(_usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    if not argv[0].startswith("-") and argv[0] not in COMMANDS:
        hint = nearest(argv[0], COMMANDS)
        print(f"{PROG}: no command {argv[0]!r}{hint}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    sub = next((a for a in argv if a in COMMANDS), None)
    prog = f"{PROG} {sub}" if sub else PROG
    stderr, held = sys.stderr, io.StringIO()
    subcommands = [
        Annotated[
            Any, tyro.conf.subcommand(name, constructor=_parsed(fn, stderr, held), description=_plain(fn.__doc__))
        ]
        for name, fn in COMMANDS.items()
    ]
    sys.stderr = held  # tyro's error box, made one line below; the command gets stderr back once it runs
    try:
        return int(tyro.cli(Union[tuple(subcommands)], prog=PROG, args=argv) or 0)  # noqa: UP007
    except SystemExit as e:
        if sys.stderr is not held or e.code in (0, None) or not held.getvalue().strip():
            raise
        sys.stderr = stderr
        print(f"{prog}: {tyro_error_line(held.getvalue(), prog)}", file=stderr)
        return 2
    except UsageError as e:
        return say_usage_error(prog, e)
    except BrokenPipeError:  # `--help | head`: the reader left; nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's own flush at exit goes nowhere
        return 0
    finally:
        if sys.stderr is held:  # not given back: tyro printed a help, or the parse failed
            sys.stderr = stderr


if __name__ == "__main__":
    sys.exit(main())

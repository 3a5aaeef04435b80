"""The RL-library examples run as written, at toy sizes: examples/sb3_ppo.py from the README's command line (the
camera), sb3_sac.py and skrl_ppo.py through their ``main`` (state), each leaving what it says it leaves; they train
with agents/configs' tuned settings (SB3's PPO from the camera too) unless told --library-defaults, and show
progress and held-out success while they run."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_sb3_ppo_example_runs_as_the_readme_writes_it(tmp_path):
    """The README's one RL-library command, word for word (the interpreter and the script's path made absolute), run
    in an empty folder so its default --out-dir lands there."""
    pytest.importorskip("stable_baselines3")
    readme = (REPO / "README.md").read_text().replace("\n  ", " ")
    found = re.findall(r"`\.venv/bin/python (examples/sb3_ppo\.py [^`]*)`", readme)
    assert len(found) == 1, found
    argv = shlex.split(found[0])
    assert "--obs" in argv and argv[argv.index("--obs") + 1] == "rgbd", argv  # the camera, as the README says
    cmd = [sys.executable, str(REPO / argv[0]), *argv[1:]]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    run = tmp_path / "runs" / "sb3_ppo"
    assert (run / "model.zip").is_file() and list(run.glob("PPO_1/events.out.tfevents.*"))
    assert "training-episode success" in out.stdout
    assert "from rgbd, 4 envs, agents/configs/sb3/ppo_rgbd.yml;" in out.stdout  # the camera's tuned config
    assert (run / "vecnormalize.pkl").is_file()  # its state-vector statistics, which the policy needs
    # the held-out check after training, and the last line saying it (SB3's ProgressCallback, as sb3_sac.py's)
    last = out.stdout.strip().splitlines()[-1]
    assert last.startswith("256 env steps in ") and re.search(r"held-out success [0-2]/2;", last), last


def test_sb3_sac_example_runs(tmp_path):
    pytest.importorskip("stable_baselines3")
    ex = load("sb3_sac")
    model = ex.main(
        ex.Args(
            obs="state", backend="cpu", total_timesteps=80, learning_starts=40, out_dir=tmp_path,
            library_defaults=True, eval_episodes=0,
        )
    )  # fmt: skip
    assert model.num_timesteps == 80 and model.replay_buffer.size() == 40
    assert (tmp_path / "model.zip").is_file()


def test_skrl_ppo_example_runs(tmp_path, capsys):
    pytest.importorskip("skrl")
    ex = load("skrl_ppo")
    agent = ex.main(
        ex.Args(
            obs="state", backend="cpu", total_timesteps=400, out_dir=tmp_path, library_defaults=True, eval_episodes=0
        )
    )
    assert agent.cfg.time_limit_bootstrap and agent.cfg.rollouts == 16
    assert list(tmp_path.rglob("events.out.tfevents.*"))  # skrl writes every 1 % of the steps: 2 of 200 here
    assert (tmp_path / "agent.pt").is_file()
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("400 env steps in ") and "env steps/s" in last and "agent.pt" in last, last


def test_an_example_stopped_by_ctrl_c_saves_its_model_and_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    """A Ctrl-C during SB3's learn (here after one 64-step rollout) still saves the model; the example says where
    in one line and exits with status 130, the shell's for an interrupt, without a traceback."""
    pytest.importorskip("stable_baselines3")
    ex = load("sb3_ppo")
    learn = ex.PPO.learn

    def interrupted(self, total_timesteps, **kwargs):
        learn(self, 64, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(ex.PPO, "learn", interrupted)
    with pytest.raises(SystemExit) as stop:
        ex.main(ex.Args(obs="state", backend="cpu", n_steps=32, total_timesteps=10_000, out_dir=tmp_path, num_envs=2))
    assert stop.value.code == 130 and (tmp_path / "model.zip").is_file()
    err = [line for line in capsys.readouterr().err.splitlines() if " - WARNING - " not in line and line.strip()]
    assert err[-1] == f"interrupted (Ctrl-C or SIGTERM) at 64 env steps; model so far: {tmp_path}/model.zip", err


@pytest.mark.parametrize(
    "sigint_ignored",
    # the background start (SIGINT ignored, as a script's `&` leaves it) is the case that once hung; the plain
    # foreground one runs with -m slow
    [pytest.param(False, marks=pytest.mark.slow), True],
    ids=["foreground", "started-by-a-script-in-background"],
)
def test_a_sigterm_to_the_group_stops_an_example_as_a_ctrl_c_does(tmp_path, terminate_group, sigint_ignored):
    """A session's end or a scheduler sends SIGTERM, often to the whole process group: the example saves the model
    learnt so far and says so in one line with exit status 130, and its worker envs, which ignore SIGTERM, print no
    BrokenPipe traceback. Also when SIGINT is ignored, as for a run a script starts with ``cmd &``: such a run once
    ignored SIGTERM too, since its Ctrl-C path went through SIGINT's handler."""
    pytest.importorskip("stable_baselines3")
    argv = [sys.executable, str(EXAMPLES / "sb3_ppo.py"), "--obs", "state", "--backend", "cpu", "--num-envs", "2"]
    argv += ["--n-steps", "32", "--total-timesteps", "1000000", "--eval-episodes", "0", "--out-dir", str(tmp_path)]
    # SB3 opens its TensorBoard log as learn() starts; 2 s more is a few rollouts in
    started = lambda: any(tmp_path.rglob("events.out.tfevents.*"))  # noqa: E731
    code, own = terminate_group(argv, started, settle_s=2, sigint_ignored=sigint_ignored)
    assert code == 130 and len(own) == 1, own
    assert re.fullmatch(rf"interrupted \(Ctrl-C or SIGTERM\) at \d+ env steps; model so far: {tmp_path}/model.zip",
                        own[0]), own  # fmt: skip
    assert (tmp_path / "model.zip").is_file() and (tmp_path / "vecnormalize.pkl").is_file()


def test_sb3_sac_example_builds_its_config_from_state(tmp_path):
    """SAC from state without flags: sac.yml's settings (4 envs, VecNormalize, gamma 0.8)."""
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import VecNormalize

    ex = load("sb3_sac")
    args = ex.Args(backend="cpu", total_timesteps=48, learning_starts=24, eval_episodes=1, out_dir=tmp_path)
    model, source, total = ex.build(args)
    model.get_env().close()
    assert source == "agents/configs/sb3/sac.yml" and total == 48
    assert model.gamma == 0.8 and model.tau == 0.01 and model.gradient_steps == 2 and model.learning_starts == 24
    assert isinstance(model.get_env(), VecNormalize) and model.get_env().num_envs == 4


# ~40 s: four worker envs and a held-out episode; test_sb3_sac_example_builds_its_config_from_state covers the config,
# test_sb3_sac_example_runs a run of the example, test_sb3_ppo_example_runs_as_the_readme_writes_it the held-out
# check and the last line naming it (SB3's ProgressCallback, the same in both examples)
@pytest.mark.slow
def test_sb3_sac_example_trains_on_its_config_from_state_and_says_how_it_goes(tmp_path, capsys):
    """SAC from state without flags: sac.yml's settings, the progress line it starts with, a held-out check at the
    end and the summary naming it."""
    pytest.importorskip("stable_baselines3")
    ex = load("sb3_sac")
    args = ex.Args(backend="cpu", total_timesteps=48, learning_starts=24, eval_episodes=1, out_dir=tmp_path)
    ex.main(args)
    out = capsys.readouterr().out
    assert "4 envs, agents/configs/sb3/sac.yml; 48 env steps, the first 24 random" in out, out
    assert "[sb3 sac] 0/48 env steps (0 %)" in out, out
    assert re.search(r"held-out success [01]/1 \(deterministic", out), out
    last = out.strip().splitlines()[-1]
    assert last.startswith("48 env steps in ") and "held-out success" in last and "model.zip" in last, last
    assert (tmp_path / "vecnormalize.pkl").is_file()


def test_skrl_ppo_example_trains_on_its_config_from_state(tmp_path, capsys):
    pytest.importorskip("skrl")
    ex = load("skrl_ppo")
    agent = ex.main(ex.Args(backend="cpu", total_timesteps=64, eval_episodes=1, out_dir=tmp_path))
    cfg = agent.cfg
    get = (lambda k: cfg[k]) if isinstance(cfg, dict) else (lambda k: getattr(cfg, k))  # noqa: E731
    assert get("rollouts") == 128 and get("discount_factor") == 0.8  # ppo_grasplift.yaml's, not PPO_CFG's 16, 0.99
    out = capsys.readouterr().out
    assert "4 envs, agents/configs/skrl/ppo_grasplift.yaml; 64 env steps" in out, out
    last = out.strip().splitlines()[-1]
    assert last.startswith("64 env steps in ") and "held-out success" in last and "agent.pt" in last, last


def test_the_documented_state_commands_say_what_the_screening_measured():
    """docs/rl_libraries.md's minutes and held-out counts for the state commands are the screening cells' (same
    configs, 4 CPU worker envs), not written from memory: SAC's at the command's env steps on its held-out curve,
    PPO's extrapolated from its cell's env steps per wall-clock second."""
    import json

    cells = json.loads((REPO / "benchmarks/results/screening/algorithms.json").read_text())["cells"]
    doc = (REPO / "docs/rl_libraries.md").read_text()
    block = doc[doc.index("## Examples") :].split("```bash")[1].split("```")[0].splitlines()
    said = {}
    for comment, command in zip(block, block[1:]):
        m = re.search(r"examples/sb3_(sac|ppo)\.py .*--obs state --total-timesteps (\d+)$", command)
        if comment.startswith("#") and m:
            said[m.group(1)] = (int(m.group(2)), comment)
    assert set(said) == {"sac", "ppo"}, block
    steps, comment = said["sac"]
    curve = cells["state/GraspLift/sb3-sac-tuned/s1"]["held_out_curve"]
    k = curve["env_steps"].index(steps)
    wins = round(curve["success"][k] * curve["episodes"][k])
    assert f"{wins}/{curve['episodes'][k]} held out at {steps:,} env steps" in comment, comment
    assert f"about {round(curve['wall_min'][k])} min" in comment, comment
    steps, comment = said["ppo"]
    cell = cells["state/GraspLift/sb3-ppo-tuned/s1"]
    assert f"about {round(steps * cell['wall_clock_s'] / cell['env_steps'] / 60)} min" in comment, comment
    assert max(cell["held_out_curve"]["success"]) == 0 and "0/30 held out" in comment, comment

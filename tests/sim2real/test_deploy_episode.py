"""Deploy, then a full episode: ``maniskill-irb120 deploy`` loads the server into the emulator over Robot Web
Services (the build the controller's options allow), the operator starts it on the pendant, and the scripted
expert runs one episode through ManiSkill's Sim2RealEnv over the channel the deployment chose (serial with no
option; TCP with 616-1, with the world zone of 608-1), against the emulator's digital twin."""

from __future__ import annotations

import gymnasium as gym
import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
pytest.importorskip("abb_robot_client")

import maniskill_irb120  # noqa: E402, F401
from maniskill_irb120.abb.deploy import shipped_rapid_dir  # noqa: E402
from maniskill_irb120.abb.emulator.rws import RWSEmulator  # noqa: E402
from maniskill_irb120.cli import main  # noqa: E402
from maniskill_irb120.experts import expert_for  # noqa: E402
from maniskill_irb120.sim2real.agent import IRB120RealAgent  # noqa: E402
from maniskill_irb120.sim2real.env import IRB120Sim2RealEnv  # noqa: E402
from maniskill_irb120.sim2real.twin import DigitalTwin  # noqa: E402

ENV_ID = "TableClearing-IRB120-v1"


@pytest.mark.parametrize("options,scheme,modules", [("", "serial", 3), ("616-1,608-1", "tcp", 4)])
def test_deploy_then_an_expert_episode_over_the_chosen_channel(tmp_path, capsys, options, scheme, modules):
    # the integrator's copies: the TCP build serves the one PC address it names, here the local client's
    for f in ("IRB120Server.mod", "IRB120Serial.mod", "IRB120Socket.mod", "IRB120Zone.sys"):
        (tmp_path / f).write_text((shipped_rapid_dir() / f).read_text())
    sock = (tmp_path / "IRB120Socket.mod").read_text()
    (tmp_path / "IRB120Socket.mod").write_text(sock.replace('"192.168.125.2"', '"127.0.0.1"'))
    with RWSEmulator(options=options) as rws:
        assert main(["deploy", "--controller", rws.url, "--yes", "--rapid-dir", str(tmp_path)]) == 0
        assert "the program is stopped" in capsys.readouterr().out
        vc = rws.controller
        assert len(vc.modules) == modules and vc.exec_state == "stopped"
        vc.start(remote=False)  # the operator: enabling device held, Start on the FlexPendant
        url, program = vc.program_url, vc.program
        assert url.startswith(f"{scheme}://")
        twin = DigitalTwin(ENV_ID, program)
        sim = gym.make(ENV_ID, obs_mode="rgbd", control_mode="pd_ee_delta_tool")
        agent = IRB120RealAgent(url, camera=twin.camera, finger_qpos=twin.finger_qpos)
        env = IRB120Sim2RealEnv(sim, agent, world=twin)
        try:
            env.reset(seed=0)
            expert = expert_for(twin.env)
            expert.reset()
            for _ in range(250):
                _, _, term, trunc, info = env.step(expert.act()[0])
                if bool(term[0]) or bool(trunc[0]):
                    break
            assert bool(info["success"][0])
        finally:
            env.close()
            twin.close()
        assert program.error is None, program.error
        assert program.zone == ("608-1" in options)

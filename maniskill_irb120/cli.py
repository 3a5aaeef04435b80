"""``maniskill-irb120`` command line (tyro subcommands, as ManiSkill's own scripts use tyro)."""

from __future__ import annotations

import sys

import tyro


def doctor(json: bool = False) -> int:
    """Check the Vulkan/render device, CUDA sim support and package versions (exit 1 if rendering fails)."""
    from maniskill_irb120.doctor import main

    return main(json_output=json)


def collect_demos(episodes: int = 10, seed: int = 0, out_dir: str = "demos", name: str = "expert",
                  obs_mode: str = "none", keep_failures: bool = False, save_video: bool = False) -> int:
    """Record scripted-expert episodes in ManiSkill's trajectory format (h5 + json)."""
    import json
    from pathlib import Path

    from maniskill_irb120.demos import collect_demos as collect

    print(json.dumps(collect(episodes, seed, Path(out_dir), name, obs_mode, not keep_failures, save_video)))
    return 0


def expert(episodes: int = 100, seed: int = 0, obs_mode: str = "state") -> int:
    """Run the scripted expert and print one JSON line (success_rate, episodes, mean_steps, ...)."""
    from maniskill_irb120.expert import Args, main as expert_main

    expert_main(Args(episodes=episodes, seed=seed, obs_mode=obs_mode))
    return 0


COMMANDS = {"doctor": doctor, "collect-demos": collect_demos, "expert": expert}


def main(argv: list[str] | None = None) -> int:
    return int(tyro.extras.subcommand_cli_from_dict(COMMANDS, args=argv) or 0)


if __name__ == "__main__":
    sys.exit(main())

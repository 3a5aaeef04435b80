"""``maniskill-irb120`` command line (tyro subcommands, as ManiSkill's own scripts use tyro)."""

from __future__ import annotations

import sys

import tyro


def doctor(json: bool = False) -> int:
    """Check the Vulkan/render device, CUDA sim support and package versions (exit 1 if rendering fails)."""
    from maniskill_irb120.doctor import main

    return main(json_output=json)


COMMANDS = {"doctor": doctor}


def main(argv: list[str] | None = None) -> int:
    return int(tyro.extras.subcommand_cli_from_dict(COMMANDS, args=argv) or 0)


if __name__ == "__main__":
    sys.exit(main())

"""Fixtures the ABB tests share."""

from __future__ import annotations

import pytest


@pytest.fixture
def rws_emulator():
    """``start(**kwargs)``: an RWS emulator serving on loopback, stopped after the test, which also fails if the
    RAPID program it ran ended in an error."""
    from maniskill_irb120.abb.emulator.rws import RWSEmulator

    emus = []

    def start(**kwargs) -> RWSEmulator:
        emu = RWSEmulator(**kwargs)
        emu.start()
        emus.append(emu)
        return emu

    yield start
    for emu in emus:
        program = emu.controller.program
        emu.stop()
        assert program is None or program.error is None, program.error

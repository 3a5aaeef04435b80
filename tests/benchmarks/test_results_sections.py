"""Every generated section of benchmarks/RESULTS.md is what its benchmark renders from the committed JSON now (rerun
the benchmark with ``--render-only`` after its JSON changes), each renderer writes its table and its command, and
``--render-only`` measures nothing. Nothing here runs a benchmark."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "benchmarks"
RESULTS = BENCH / "RESULTS.md"
DATA = BENCH / "results"


@pytest.fixture(scope="module")
def results_md(bench_script):
    return bench_script("lib.report")


def rendered(tmp_path: Path, update, *args) -> str:
    """What ``update(*args, results=...)`` leaves in a copy of RESULTS.md."""
    copy = tmp_path / "RESULTS.md"
    shutil.copy(RESULTS, copy)
    update(*args, results=copy)
    return copy.read_text()


# ----------------------------------------------------------------------------- each renderer writes its table
def test_adapter_section_has_every_channel_and_the_command(bench_script):
    mod = bench_script("adapter_latency")
    report = json.loads((DATA / "adapter_latency.json").read_text())
    text = mod.section(report, DATA / "adapter_latency.json")
    assert text.startswith(mod.HEAD + "\n\n")
    assert f"Command: `python {report['command']}`" in text
    for label in ("TCP loopback", "pty, no line speed", "pty paced at 115200 baud", "pty paced at 9600 baud"):
        assert f"| {label} (emulator) |" in text
    tcp = report["round_trip"][0]
    assert f"| {tcp['mean_ms']:.2f} | {tcp['p50_ms']:.2f} |" in text
    assert "[`results/adapter_latency.json`](results/adapter_latency.json)" in text
    assert "49.0 ms at 9600 baud" in text


def test_sysid_section_has_every_case_and_the_command(bench_script):
    mod = bench_script("sysid_recovery")
    report = json.loads((DATA / "sysid_recovery.json").read_text())
    text = mod.section(report, DATA / "sysid_recovery.json")
    assert f"Command: `python {report['command']}`" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == len(mod.CASES) == len(report["rows"])
    assert rows[0].startswith("| 0 | 0.0 ± ")  # the no-injection case is the emulator's own latency, by definition
    assert f"{1000 * report['own_latency_s']:.1f} ms here" in text


def test_sim2real_section_has_a_table_per_run_and_pools_shared_cells(bench_script):
    mod = bench_script("sim2real_gap")
    text = mod.section(list(mod.SECTION_JSONS))
    assert text.count("| policy | shift | sim success |") == len(mod.SECTION_JSONS)
    for path in mod.SECTION_JSONS:
        assert f"[`results/{path.name}`](results/{path.name})" in text
    assert "| expert | none | 100 % | 100 % |" in text and "test the adapter path" in text
    # the two seed ranges of the two committed policies, pooled: 60 episodes a cell
    assert "| camera-dr-mount-nolat | all together | 2 | 40/60 | 42/60 |" in text
    assert "| camera-dr-mount-nolat-s43 | camera mount | 2 | 46/60 | 47/60 |" in text
    # the recorded command lost the quotes around row names; the page's copy runs as shown
    assert "--shifts 'camera mount' 'all together' --out" in text


def test_sim2real_requotes_row_names_and_keeps_quoted_commands(bench_script):
    mod = bench_script("sim2real_gap")
    old = "benchmarks/sim2real_gap.py --policy a.pt --shifts none camera mount x0.25 lighting & colours/textures"
    assert mod.requoted(old + " --json x.json") == (
        "python benchmarks/sim2real_gap.py --policy a.pt --shifts none 'camera mount x0.25' "
        "'lighting & colours/textures' --json x.json"
    )
    new = "python benchmarks/sim2real_gap.py --shifts 'camera mount' 'all together, mount corrected' --episodes 3"
    assert mod.requoted(new) == new
    assert mod.requoted("benchmarks/sim2real_gap.py --episodes 10") == "python benchmarks/sim2real_gap.py --episodes 10"


def test_rllib_and_learner_sections_have_their_tables_and_commands(bench_script):
    rllib = bench_script("rllib_speed")
    report = json.loads((DATA / "rllib_speed.json").read_text())
    text = rllib.section(report, DATA / "rllib_speed.json")
    assert f"Command: `{report['command']}`" in text and text.count("| rllib PPO |") == 6
    learner = bench_script("learner_speed")
    report = json.loads((DATA / "learner_speed.json").read_text())
    text = learner.section(report, DATA / "learner_speed.json")
    assert f"Command: `{report['command']}`" in text and "| bf16 encoder |" in text
    gpu = json.loads((DATA / "learner_speed_h200_cuda.json").read_text())
    with pytest.raises(ValueError, match="CPU figures"):  # a GPU run has its own section, kept apart
        learner.section(gpu, DATA / "learner_speed_h200_cuda.json")


def test_gpu_section_has_the_machine_the_checks_and_the_learner_table(results_md, bench_script):
    mod = bench_script("gpu_acceptance")
    report = json.loads((DATA / "gpu_acceptance.json").read_text())
    text = mod.section(report, DATA / "gpu_acceptance.json", [mod.LEARNER_JSONS])
    assert text.startswith(mod.HEAD + "\n\n")
    env = report["environment"]
    for fact in (env["device"], f"driver {env['driver']}", f"CUDA {env['cuda_runtime']}", f"commit `{env['commit']}`",
                 f"sapien {env['version_sapien']}", report["date"]):  # fmt: skip
        assert fact in text.split("\n\n")[1], fact
    for check in report["checks"]:
        assert f"| {check['name']} | {'**FAILED**' if check['ok'] is False else 'skipped'} |" in text
    # the failed check, in one line: the exception's repr shortened, the fix kept whole
    assert "fetching it failed (ConnectionError …); without internet access unzip https://" in text
    assert "linux-so.zip into /root/.sapien/physx/105.1-physx-5.3.1.patch0 |" in text
    assert "`physx_cuda` did not start there: `physx gpu library` failed, so the other 11 checks" in text
    assert "No steps/s were timed: at 512, 1024, 4096 envs" in text
    # the JSON predates recorded commands: the page says so instead of inventing one
    assert "The JSON records no command; `python -m benchmarks.gpu_acceptance --jobs 8 --json-path " in text
    for path in (DATA / "gpu_acceptance.json", *mod.LEARNER_JSONS):
        assert results_md.raw_link(path) in text
        if path.name.startswith("learner"):
            assert f"`{results_md.recorded_command(json.loads(path.read_text())['command'])}`" in text
    assert "| fp32 | 4.9 | 22.0 | 4.5x |" in text and "| bf16 encoder | 5.3 | 12.9 | 2.5x |" in text
    assert "median of 7 rounds" in text and "(../docs/notes/gpu-h200.md)" in text


def test_gpu_section_of_a_passing_report_and_bad_learner_pairs(tmp_path, bench_script):
    mod = bench_script("gpu_acceptance")
    report = json.loads((DATA / "gpu_acceptance.json").read_text())
    report["command"] = "python benchmarks/gpu_acceptance.py --jobs 8 --json-path 'a b.json'"
    report["checks"] = [dict(c, ok=True, status="PASS", reason="fine | well") for c in report["checks"]]
    report["throughput"] = [dict(num_envs=512, env_steps_per_s=12345.6, gpu_mem_used_gb=3.21),
                            dict(num_envs=4096, error="RuntimeError: out of memory")]  # fmt: skip
    text = mod.section(report, tmp_path / "g.json")
    assert f"Command: `{report['command']}`." in text and "Every check that ran passed (12 of 12; 0 skipped)" in text
    assert "| agents.ppo | ok | fine \\| well |" in text
    assert "| 512 | 12346 | 3.2 |" in text and "| 4096 | RuntimeError: out of memory | |" in text
    assert "did not start" not in text and "| configuration |" not in text
    cuda, cpu = mod.LEARNER_JSONS
    with pytest.raises(ValueError, match="a CUDA run and a CPU run"):
        mod.section(report, tmp_path / "g.json", [(cpu, cpu)])
    other = tmp_path / "other_machine.json"
    other.write_text(json.dumps(dict(json.loads(cpu.read_text()), machine="elsewhere")))
    with pytest.raises(ValueError, match="different machines"):
        mod.section(report, tmp_path / "g.json", [(cuda, other)])


def test_one_line_keeps_what_to_do_and_cuts_the_rest(bench_script):
    mod = bench_script("gpu_acceptance")
    assert mod.one_line("short (kept as is)\nsecond line") == "short (kept as is)"
    nested = "x failed (OSError: " + "y" * 80 + " (inner) more); do this"
    assert mod.one_line(nested) == "x failed (OSError …); do this"
    assert mod.one_line("a (unclosed " + "z" * 10) == "a (unclosed " + "z" * 10
    cut = mod.one_line("w" * 500, limit=20)
    assert len(cut) == 20 and cut.endswith("…")
    assert mod.one_line("a | b") == "a \\| b"


# ----------------------------------------------------------------------------- RESULTS.md is what they render
@pytest.mark.parametrize(
    "name, args",
    [
        ("adapter_latency", (DATA / "adapter_latency.json",)),
        ("sysid_recovery", (DATA / "sysid_recovery.json",)),
        ("rllib_speed", (DATA / "rllib_speed.json",)),
        ("learner_speed", (DATA / "learner_speed.json",)),
        ("camera_ppo_split", (DATA / "camera_ppo_split.json",)),
        ("gpu_acceptance", (DATA / "gpu_acceptance.json",)),
        ("sim_speed", (DATA / "sim_speed.json",)),
        ("sim2real_gap", None),
    ],
)
def test_results_md_section_is_what_the_benchmark_renders(name, args, tmp_path, results_md, bench_script):
    mod = bench_script(name)
    args = args or (list(mod.SECTION_JSONS),)
    assert rendered(tmp_path, mod.update_results, *args) == RESULTS.read_text(), (
        f"benchmarks/RESULTS.md's section {mod.HEAD!r} is not what the JSON renders: "
        f"python benchmarks/{name}.py --render-only"
    )
    assert results_md.read_section(RESULTS, mod.HEAD) is not None


@pytest.mark.parametrize("env_id", ["TableClearing-IRB120-v1", "GraspLift-IRB120-v1", "StackCube-IRB120-v1"])
def test_results_md_learning_sections_are_what_learning_renders(env_id, tmp_path, bench_script):
    learning = bench_script("learning")
    report = json.loads((learning.ROOT / learning.default_out_dir(env_id) / "learning.json").read_text())
    update = lambda results: learning.update_results(report, learning.markdown(report["rows"]), results)
    assert rendered(tmp_path, update) == RESULTS.read_text(), (
        f"python benchmarks/learning.py --render-only --env-id {env_id}"
    )


def test_no_issue_numbers_in_the_generated_sections(results_md, bench_script):
    names = ("adapter_latency", "sysid_recovery", "sim2real_gap", "rllib_speed", "learner_speed", "gpu_acceptance")
    names += ("sim_speed", "camera_ppo_split")
    heads = [bench_script(n).HEAD for n in names]
    for head in heads:
        assert "issue" not in results_md.read_section(RESULTS, head).lower(), head


# ----------------------------------------------------------------------------- --render-only measures nothing
@pytest.mark.parametrize("name", ["adapter_latency", "sysid_recovery"])
def test_render_only_reads_the_committed_json_and_measures_nothing(name, monkeypatch, bench_script):
    mod = bench_script(name)
    written = []
    monkeypatch.setattr(mod, "update_results", lambda path: written.append(path))
    for runner in ("measure", "run"):  # adapter_latency's and sysid_recovery's measurement
        if hasattr(mod, runner):
            monkeypatch.setattr(mod, runner, lambda *a, **k: pytest.fail("--render-only measured"))
    report = mod.main(mod.Args(render_only=True))
    assert written == [mod.RESULTS_JSON] and report == json.loads(mod.RESULTS_JSON.read_text())


def test_sim2real_render_only_runs_no_cell_and_adds_json(monkeypatch, tmp_path, bench_script):
    mod = bench_script("sim2real_gap")
    written = []
    monkeypatch.setattr(mod, "update_results", lambda paths: written.append(paths))
    monkeypatch.setattr(mod, "evaluate", lambda cfg: pytest.fail("--render-only ran a cell"))
    mod.main(mod.Args(render_only=True))
    extra = tmp_path / "new.json"
    extra.write_text("{}")  # --render-only refuses a --json that is not there (check)
    mod.main(mod.Args(render_only=True, json=extra))
    mod.main(mod.Args(render_only=True, json=mod.SECTION_JSONS[0]))  # already shown: not twice
    assert written == [list(mod.SECTION_JSONS), [*mod.SECTION_JSONS, extra], list(mod.SECTION_JSONS)]
    with pytest.raises(ValueError, match="name the run's --json"):
        mod.main(mod.Args(update_results=True))


def test_a_run_with_update_results_renders_its_own_json(monkeypatch, tmp_path, bench_script):
    """adapter_latency and sysid_recovery end to end with their measurements faked: the JSON the run writes is
    what the section shows, with the run's command quoted as typed."""
    adapter, sysid = bench_script("adapter_latency"), bench_script("sysid_recovery")
    copy = tmp_path / "RESULTS.md"
    shutil.copy(RESULTS, copy)
    monkeypatch.setattr(sys, "argv", ["benchmarks/x.py", "--steps", "3", "--note", "two words"])

    def fake_measure(channel, steps, cost_us, baud=None):
        name = channel if baud is None else f"{channel} @ {baud} baud"
        return dict(channel=name, statements_per_step=600.0, statement_ms_per_step=6.0, mean_ms=12.345,
                    p50_ms=1.0, p95_ms=2.0, max_ms=3.0)  # fmt: skip

    def fake_fit(latency_ms, scale, steps, seed):
        return dict(latency_s=0.02 + latency_ms / 1000, speed_scale=scale, rms_joint_error_fit_rad=0.001,
                    rms_joint_error_nominal_rad=0.005)  # fmt: skip

    for mod, fake, name in ((adapter, fake_measure, "measure"), (sysid, fake_fit, "run")):
        real_update = mod.update_results
        monkeypatch.setattr(mod, name, fake)
        monkeypatch.setattr(mod, "update_results", lambda path, real_update=real_update: real_update(path, copy))
        out = tmp_path / f"{mod.__name__}.json"
        mod.main(mod.Args(steps=3, json=out, update_results=True))
        section = bench_script("lib.report").read_section(copy, mod.HEAD)
        assert section == mod.section(json.loads(out.read_text()), out)
        assert f"Command: `python -m {mod.__name__} --steps 3 --note 'two words'`" in section
    assert "| TCP loopback (emulator) | 600 | 6.00 | 12.35 |" in copy.read_text()
    assert "| 40 | 40.0 ± 0.0 | 0.60 | 0.600 ± 0.000 | 1.00 / 5.00 |" in copy.read_text()


def test_gpu_render_only_needs_no_cuda_and_runs_no_check(monkeypatch, tmp_path, bench_script):
    """``gpu_acceptance.py --render-only`` on a machine without CUDA: no check starts, the section is the
    committed one."""
    import torch

    from maniskill_irb120.diagnostics import doctor

    mod = bench_script("gpu_acceptance")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(doctor, "gpu_main", lambda **k: pytest.fail("--render-only ran the checks"))
    monkeypatch.setattr(doctor, "gpu_report", lambda **k: pytest.fail("--render-only ran the checks"))
    copy = tmp_path / "RESULTS.md"
    shutil.copy(RESULTS, copy)
    real_update = mod.update_results
    written = []
    monkeypatch.setattr(mod, "update_results", lambda path: (written.append(path), real_update(path, copy)))
    assert mod.main(mod.Args(render_only=True)) == 0
    assert written == [mod.RESULTS_JSON] and copy.read_text() == RESULTS.read_text()


def test_gpu_run_with_update_results_records_its_command_and_renders_its_json(monkeypatch, tmp_path, bench_script):
    """The acceptance run with the doctor faked: the JSON it leaves carries the command as typed, and the section
    shows that JSON, failed checks and all."""
    from maniskill_irb120.diagnostics import doctor

    mod = bench_script("gpu_acceptance")
    report = json.loads((DATA / "gpu_acceptance.json").read_text())
    report["checks"][1] = dict(report["checks"][1], ok=False, status="FAIL", reason="exit status 1: boom")

    def fake_gpu_main(json_path, **kw):
        Path(json_path).write_text(json.dumps(report))
        return 1

    monkeypatch.setattr(doctor, "gpu_main", fake_gpu_main)
    out = tmp_path / "my report.json"
    monkeypatch.setattr(sys, "argv", ["benchmarks/gpu_acceptance.py", "--jobs", "8", "--json-path", str(out)])
    copy = tmp_path / "RESULTS.md"
    shutil.copy(RESULTS, copy)
    real_update = mod.update_results
    monkeypatch.setattr(mod, "update_results", lambda path: real_update(path, copy))
    assert mod.main(mod.Args(jobs=8, json_path=out, update_results=True)) == 1
    saved = json.loads(out.read_text())
    assert saved["command"] == f"python -m benchmarks.gpu_acceptance --jobs 8 --json-path '{out}'"
    section = bench_script("lib.report").read_section(copy, mod.HEAD)
    assert section == mod.section(saved, out, [mod.LEARNER_JSONS])
    assert (
        f"Command: `{saved['command']}`." in section and "| obs modes | **FAILED** | exit status 1: boom |" in section
    )
    assert copy.read_text().count(mod.HEAD) == 1

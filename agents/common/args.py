"""The flags every trainer shares (``RunArgs``: task, seed, the env-step budget and its wall guard, evaluation,
selection, backend, run folder, resume, loggers), ``--recipe`` expansion, and the command line's end: a flag that
cannot run, or one that was removed (:data:`RENAMED`), is one line on stderr and exit status 2 (:func:`entry`).
Each trainer's ``Args`` extends RunArgs and only overrides a default where its recipe needs another one.
``--recipe NAME`` runs a named recipe of ``agents/recipes.py`` (its flags first, the command line's after them,
so an explicit flag wins). See docs/training.md."""

from __future__ import annotations

import ast
import contextlib
import io
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import UnionType
from typing import Literal, Optional, TypeVar, Union, get_args, get_origin, get_type_hints

import tyro

from agents.recipes import RECIPES
from maniskill_irb120.errors import UsageError, nearest, terminate_as_interrupt, usage_errors

A = TypeVar("A", bound="RunArgs")


@dataclass
class RunArgs:
    env_id: str = "TableClearing-IRB120-v1"
    """the task (a registered ManiSkill env id)"""
    seed: int = 1
    """seeds torch/numpy and the training episodes (always below the held-out evaluation seeds)"""
    total_env_steps: Optional[int] = None
    """the budget: a step of training (a PPO iteration, a SAC env step and its updates, a DAgger round) starts only
    while fewer env steps than this are done, counting the run's before a --resume (None: the trainer's own)"""
    max_minutes: Optional[float] = None
    """a wall-clock guard: training stops once its next step would end past this many minutes (counting the run's
    before a --resume); a run it stops before --total-env-steps says so ("stopped_early")"""
    budget_min: Optional[float] = None
    """the old name of --max-minutes (kept for the committed runs and recipes that pass it; --max-minutes wins)"""
    eval_episodes: int = 100
    """the held-out evaluation after training and of --evaluate: deterministic episodes on held-out seeds
    (agents.common.EVAL_SEED onwards; 0: none after training)"""
    select_episodes: int = 0
    """checkpoint selection: every --select-freq steps of training and after the last, the policy on this many
    validation seeds (agents.common.VALIDATION_SEED onwards); the best is checkpoints/best.pt, and the held-out
    evaluation scores it instead of the last weights (0: no selection). Its episodes count in --max-minutes"""
    select_freq: int = 25
    """steps of training (PPO iterations, DAgger rounds, SAC env steps) between two selection evaluations"""
    curve_points: int = 0
    """a held-out curve while training: the policy as it is on --curve-episodes held-out seeds (EVAL_SEED onwards)
    after the step that crosses each tenth (for 10) of --total-env-steps and a quarter, its time left out of the
    budget clock; kept in summary.json's held_out_curve (0: none; it needs --total-env-steps)"""
    curve_episodes: int = 30
    """held-out episodes of each --curve-points evaluation"""
    device: str = "auto"
    """torch device of the learner (auto: CUDA when available)"""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """the envs: gpu (one GPU-batched env), cpu (worker processes) or auto (gpu when CUDA is available)"""
    exp_name: Optional[str] = None
    """run folder under --runs-dir (default: algorithm__env__obs__seed__time)"""
    runs_dir: Path = Path("runs")
    """TensorBoard logs, checkpoints and summary.json go to runs_dir/exp_name"""
    resume: Optional[Path] = None
    """continue a run from this checkpoint (networks, optimisers, data, counters, RNG)"""
    evaluate: bool = False
    """only evaluate --checkpoint on held-out episodes (videos + summary.json)"""
    checkpoint: Optional[Path] = None
    """the checkpoint --evaluate reads"""
    capture_video: bool = True
    """--evaluate: record an mp4 per episode"""
    progress: bool = True
    """a tqdm progress bar"""
    wandb: bool = False
    """also log to Weights & Biases (imported only when set; WANDB_MODE=offline: to RUN_DIR/wandb, no account)"""
    comet: bool = False
    """also log to Comet, as the original report did (imported only when set; COMET_START_ONLINE=false: an
    archive in RUN_DIR/comet, no account)"""
    wandb_project: str = "maniskill_irb120"
    """the W&B project"""
    comet_project: str = "maniskill_irb120"
    """the Comet project"""
    recipe: Optional[str] = None
    """a named recipe of agents/recipes.py: its flags for --env-id first, this command line's after them
    (so they override); only this trainer's single-stage recipes"""
    env_kwargs: dict = field(default_factory=dict)
    """extra gym.make keyword arguments, e.g. domain randomisation ranges; a value that reads as a Python
    literal is one (``reconfiguration_freq 5`` an int), any other stays a string"""

    def __post_init__(self) -> None:
        # the command line hands every value over as a string; ManiSkill's counters need numbers
        self.env_kwargs = {k: _literal(v) for k, v in self.env_kwargs.items()}


def _literal(value):
    if not isinstance(value, str):
        return value
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return value


def _flag(argv: list[str], name: str) -> Optional[str]:
    """The last value given to ``--name`` in ``argv`` (``--name V`` or ``--name=V``), or None."""
    value = None
    for i, a in enumerate(argv):
        if a == name and i + 1 < len(argv):
            value = argv[i + 1]
        elif a.startswith(name + "="):
            value = a.split("=", 1)[1]
    return value


def recipe_argv(module: str, argv: list[str], env_id: str, seed: int) -> list[str]:
    """``argv`` with ``--recipe NAME`` expanded: the recipe's flags for the task (``--env-id``, else ``env_id``)
    and seed (``--seed``, else ``seed``) first, then its env-step budget on that task where the committed runs
    give one (``ENV_STEP_BUDGETS``), ``argv`` after them (a ``--total-env-steps`` given overrides it). A recipe
    of another trainer, an unknown name or a two-stage recipe (its base is another run: ``benchmarks/learning.py``
    chains the two) is refused, naming the problem and this trainer's recipes."""
    name = _flag(argv, "--recipe")
    if name is None:
        return list(argv)
    valid = sorted(r for r, recipe in RECIPES.items() if recipe.trainer == module and recipe.base is None)
    if name not in RECIPES:
        raise UsageError(
            f"--recipe {name!r}: no such recipe{nearest(name, valid)}; {module}'s recipes: {', '.join(valid)}"
        )
    if RECIPES[name].trainer != module:
        raise ValueError(
            f"--recipe {name}: a recipe of {RECIPES[name].trainer}, not of {module}; {module}'s recipes: "
            f"{', '.join(valid)}"
        )
    base = RECIPES[name].base
    if base is not None:
        raise ValueError(
            f"--recipe {name}: a two-stage recipe (a {base.recipe} run first, its checkpoint handed on by "
            f"--{base.hand_on}); run it with python -m benchmarks.learning --recipes {name}, or the two runs by "
            f"hand; {module}'s recipes: {', '.join(valid)}"
        )
    env = _flag(argv, "--env-id") or env_id
    resolved = RECIPES[name].for_task(env)
    budget = [] if resolved.env_steps is None else ["--total-env-steps", str(resolved.env_steps[0])]
    return [*resolved.argv(_flag(argv, "--seed") or seed), *budget, *argv]


BUDGET_FLAGS = {"total_env_steps": "env steps", "max_minutes": "minutes", "budget_min": "minutes"}
"""the budget and guard fields, and their units"""

RENAMED = {
    "--total-timesteps": "use --total-env-steps",
    "--timesteps": "use --total-env-steps",
    "--out-dir": "use --runs-dir",
    "--max-wall-s": "use --max-minutes (in minutes)",
    "--num-eval-episodes": "use --eval-freq-episodes (for --evaluate: --eval-episodes)",
    "--partial-reset": "training always auto-resets finished envs",
    "--no-partial-reset": "training always auto-resets finished envs",
}
"""flags that are gone, and what takes their place: given, they end the command line with one line naming it"""


def check_renamed(argv: list[str]) -> None:
    """A :class:`UsageError` naming the flag that replaced a removed one in ``argv``."""
    for i, a in enumerate(argv):
        name = a.split("=", 1)[0]
        if name in RENAMED:
            raise UsageError(f"{name} was removed; {RENAMED[name]}")
        if a.startswith("--evaluate=") or (a == "--evaluate" and i + 1 < len(argv) and not argv[i + 1].startswith("-")):
            raise UsageError("--evaluate takes no value; name the checkpoint with --checkpoint PATH")


def check_budget(args) -> None:
    """ValueError naming the flag when a budget or guard is zero or negative: such a run would train nothing, write
    a checkpoint and exit 0, which reads as success to whoever chains runs; so too for a selection that cannot
    run (its episodes are budgeted time), and for whatever the trainer's ``Args.check()`` refuses (flags that
    cannot run together)."""
    for name, unit in BUDGET_FLAGS.items():
        value = getattr(args, name, None)
        if value is not None and not value > 0:
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"{flag} must be a positive number of {unit}, got {value}")
    episodes, freq = getattr(args, "select_episodes", 0), getattr(args, "select_freq", 1)
    if episodes < 0 or freq < 1:
        raise ValueError(f"--select-episodes must be >= 0 and --select-freq >= 1, got {episodes} and {freq}")
    points, curve_episodes = getattr(args, "curve_points", 0), getattr(args, "curve_episodes", 1)
    if points < 0 or curve_episodes < 1:
        raise ValueError(f"--curve-points must be >= 0 and --curve-episodes >= 1, got {points} and {curve_episodes}")
    if points and getattr(args, "total_env_steps", None) is None and not getattr(args, "evaluate", False):
        raise ValueError("--curve-points takes its points at shares of --total-env-steps: give --total-env-steps")
    check = getattr(args, "check", None)
    if callable(check):  # a trainer's own rules for flags that cannot run together
        check()


def cli(args_type: type[A], module: str, argv: Optional[list[str]] = None, *, one_line: bool = False) -> A:
    """A trainer's command line (``sys.argv`` by default) parsed into ``args_type``, ``--recipe`` expanded first.
    With ``--resume CKPT`` every flag the command line leaves out is the resumed run's own, read from the checkpoint
    (:func:`resumed_args`): ``--resume`` alone continues the run as it was started, and a flag given again (a longer
    ``--total-env-steps``) overrides it. A zero or negative budget is a ValueError (:func:`check_budget`), and so,
    with ``one_line``, is tyro's own parse error (else its panel and exit 2)."""
    argv = sys.argv[1:] if argv is None else argv
    check_renamed(argv)
    parse = _parse if one_line else (lambda t, a, **kw: tyro.cli(t, args=a, **kw))
    resume = _flag(argv, "--resume")
    if resume is None or resume == "None":
        args = parse(args_type, recipe_argv(module, argv, args_type.env_id, args_type.seed))
    else:
        started = resumed_args(args_type, Path(resume))
        full = recipe_argv(module, argv, started.env_id, started.seed)
        # tyro reads a dict field whose default has keys as fixed options (--env-kwargs.randomization V), which would
        # refuse the recipe's own --env-kwargs KEY V: parse against an empty one and keep the run's unless given
        kept = {f.name: v for f in fields(started) if f.init and isinstance(v := getattr(started, f.name), dict) and v}
        args = parse(args_type, full, default=replace(started, **{name: {} for name in kept}))
        given = {name for name in kept if any(a == _dashed(name) or a.startswith(_dashed(name) + "=") for a in full)}
        args = replace(args, **{name: v for name, v in kept.items() if name not in given})
    check_budget(args)
    return args


def _dashed(name: str) -> str:
    return "--" + name.replace("_", "-")


def entry(
    args_type: type[A], module: str, main: Callable[[A], object], argv: Optional[list[str]] = None, recipes: bool = True
):
    """A trainer's ``python -m``: :func:`cli` (``recipes`` False: tyro alone, for a trainer without ``--recipe`` and
    with a ``--resume`` of its own), then ``main``. A command line that cannot run ends before any env is built with
    one line on stderr and exit status 2, not a traceback or tyro's boxed panel, so that a script chaining runs reads
    one reason (errors of the run itself keep their traceback)."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        if recipes:
            args = cli(args_type, module, argv, one_line=True)
        else:
            check_renamed(argv)
            args = _parse(args_type, argv)
            check_budget(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"{module}: error: {' '.join(str(e).split())}", file=sys.stderr)
        raise SystemExit(2) from None
    try:  # a SIGTERM is a Ctrl-C, and the loop saves latest.pt on its way out
        with usage_errors(module), terminate_as_interrupt():  # what only the run finds: one line too
            return main(args)
    except KeyboardInterrupt:  # the loop has saved latest.pt on its way out (its finally); the rest is noise
        print(f"{module}: interrupted; --resume RUN/checkpoints/latest.pt continues the run", file=sys.stderr)
        raise SystemExit(130) from None
    except ModuleNotFoundError as e:
        if e.name not in EXTRAS:
            raise
        print(f"{module}: error: {e.name} is not installed; the trainers need the rl extras: bash scripts/setup.sh rl",
              file=sys.stderr)  # fmt: skip
        raise SystemExit(2) from None


EXTRAS = ("tensorboard", "tqdm")
"""the modules of the trainers' extras (``pyproject.toml``'s ``rl``), which a plain setup does not install"""


def _parse(args_type: type[A], argv: list[str], **kw) -> A:
    """tyro's parse, its error (a multi-line panel on stderr, then exit 2) turned into ValueError with the panel's
    first section on one line; --help and its exit 0 are left alone."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return tyro.cli(args_type, args=argv, **kw)
    except SystemExit as e:
        if e.code in (0, None):
            sys.stderr.write(err.getvalue())
            raise
        raise ValueError(_one_line(err.getvalue()) or f"bad command line (tyro exit {e.code})") from None


def _one_line(panel: str) -> str:
    """A tyro error panel's first section (the reason) as one line: its title, frame, rules and line breaks removed
    (a rule is a run of dashes, which rich draws as box lines on a terminal and as ASCII elsewhere)."""
    sections: list[list[str]] = [[]]
    for line in panel.splitlines():
        if _RULE.search(line):
            sections.append([])
            continue
        text = line.strip().strip("│|┃").strip()
        if text:
            sections[-1].append(text)
    found = [s for s in sections if s]
    if len(found) > 1 and len(found[0]) == 1 and found[0][0].lower().endswith("error"):
        found = found[1:]  # the panel's title ("Value error") on a line of its own, as rich draws it off a terminal
    return " ".join(" ".join(found[0] if found else []).split())


_RULE = re.compile(r"[─━═-]{10,}")


def resumed_args(args_type: type[A], path: Path) -> A:
    """The arguments the run whose checkpoint is ``path`` was started with (every trainer's checkpoint keeps them,
    as JSON: ``agents.common.run.checkpoint``), as ``args_type``; a field the checkpoint predates keeps its default.
    A missing file, or one without arguments, is refused by name."""
    from agents.common.checkpoints import migrate, read_checkpoint

    if not path.is_file():
        raise FileNotFoundError(f"--resume: checkpoint {path} does not exist")
    saved = read_checkpoint(path)
    if isinstance(saved, dict) and "format" in saved:
        migrate(saved)
    saved = saved.get("args") if isinstance(saved, dict) else None
    if not isinstance(saved, dict):
        raise ValueError(f"--resume {path}: the file holds no run arguments (not a trainer's latest.pt?)")
    hints = get_type_hints(args_type)
    values = {f.name: _from_json(hints[f.name], saved[f.name]) for f in fields(args_type) if f.init and f.name in saved}
    return args_type(**values)


def _from_json(hint, value):
    """``value`` as JSON kept it (a path as a string, a tuple as a list) back as the field's type ``hint``."""
    if value is None:
        return None
    options = get_args(hint) if get_origin(hint) in (Union, UnionType) else (hint,)
    for option in (o for o in options if o is not type(None)):
        kind = get_origin(option) or option
        if kind is Path:
            return Path(value)
        if kind is tuple:
            return tuple(value)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
    return value

"""A recipe's budget in a benchmark run: env steps (``--total-env-steps``, or the committed runs' own from
``agents.recipes.ENV_STEP_BUDGETS``) with minutes as a guard, or the minutes the committed rows were held to, and
what a two-stage recipe's second stage gets of it. ``args`` is any benchmark's arguments with the fields read here."""

from __future__ import annotations

from typing import Optional

from agents.recipes import RECIPES


def budget_for(recipe: str, args) -> float:
    """Minutes per run of ``recipe``: the override of its budget kind (``--budget-min`` short, ``--long-budget-min``,
    ``--rl-budget-min``, ``--vision-budget-min``) where given, else the recipe's own on the task."""
    r = RECIPES[recipe]
    kinds = dict(short=args.budget_min, long=args.long_budget_min, rl=args.rl_budget_min, vision=args.vision_budget_min)
    return kinds[r.budget] or r.minutes(args.env_id)


def steps_for(recipe: str, args) -> Optional[tuple[int, Optional[int]]]:
    """(env steps per run of ``recipe``, its first stage's for a two-stage one), or None for a run budgeted in minutes
    (:func:`budget_for`): ``--total-env-steps``, else with ``--env-step-budgets`` the committed runs' env steps on the
    task (``agents.recipes.ENV_STEP_BUDGETS``; a recipe without them is refused by name, before any run)."""
    committed = RECIPES[recipe].for_task(args.env_id).env_steps
    if args.total_env_steps is not None:
        return args.total_env_steps, base_steps(recipe, args.env_id, args.total_env_steps)
    if not args.env_step_budgets:
        return None
    if committed is None:
        raise ValueError(
            f"--env-step-budgets: {recipe} has no committed runs on {args.env_id} to take its env steps from "
            "(agents.recipes.ENV_STEP_BUDGETS); give --total-env-steps"
        )
    return committed


def base_steps(recipe: str, env_id: str, total: int) -> Optional[int]:
    """A two-stage recipe's first-stage env steps of ``total``: the share its committed runs on ``env_id`` did, else
    its base's share; None for a single-stage recipe."""
    r = RECIPES[recipe].for_task(env_id)
    if r.base is None:
        return None
    share = r.env_steps[1] / r.env_steps[0] if r.env_steps else r.base.share
    return max(1, round(share * total))


def budget_flags(minutes: Optional[float], env_steps: Optional[int]) -> list[str]:
    """A trainer's budget flags: ``--total-env-steps`` with ``minutes`` as its ``--max-minutes`` guard (if any), or,
    for a run budgeted in minutes, ``--budget-min`` as the committed runs were started."""
    if env_steps is None:
        return ["--budget-min", f"{minutes:.4g}"]
    return ["--total-env-steps", str(env_steps)] + ([] if minutes is None else ["--max-minutes", f"{minutes:.4g}"])


def rest_of(total: Optional[float], spent: float) -> Optional[float]:
    """What a two-stage run's second stage gets of ``total`` (minutes or env steps) after its first spent ``spent``:
    at least 2 % of it, so that an overrun of the first shows in the row and the second still runs."""
    return None if total is None else max(total - spent, 0.02 * total)

"""``icco instruct "TEXT" checkpoint=PATH``: run trained policies with language instructions.

    icco instruct "Go right" checkpoint=runs/icco/.../checkpoint.pt
    icco instruct "Go right; Move top; Gather center; Spread out" eval.checkpoints='[a.pt,b.pt]'
    icco instruct "Go right" checkpoint=qmix.pt llm.prompt=tap          # QMIX-TAP (paper Sec. V-D)
    icco instruct "Go right" checkpoint=... llm=openai                   # GPT-4o, as in the paper

Instructions separated by ``;`` are given one after the other, ``eval.steps`` (145) steps
each, in one episode per trial; the planner (``cfg.llm``) is prompted once per instruction
with the robots' positions at that moment, and its plan is served to the robots as the walks
they trained on (``eval.plan``; :mod:`icco_torchrl.instructions.serving`). How the planner read
each instruction is printed, with the words it did not understand. The
metrics, tables and figures are those of ``icco eval`` (one segment per instruction), written
to ``eval.out_dir`` or ``instruct_<instructions>_<hash>/`` next to the checkpoint(s) (under
``runs/<checkpoint name>/`` for checkpoints that ship with the project). A remote
model that never replies (down, bad key, timeouts) ends the command with one line and exit
code 2, unless ``llm.fallback_on_error=true``.
"""

from __future__ import annotations

import hashlib
import json
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig

from icco_torchrl import methods
from icco_torchrl.commands import Command, clean_errors, results_beside_checkpoint, results_dir
from icco_torchrl.evaluation.runner import (
    evaluate_checkpoints,
    find_checkpoints,
    slug,
    write_report,
)
from icco_torchrl.instructions.llm import LLMPlanner, LLMUnavailable
from icco_torchrl.instructions.planner import check_understood, how_read, is_offline
from icco_torchrl.instructions.sources import language_schedule, split_instructions


def out_dir_name(instructions: list[str]) -> str:
    """``instruct_<slug>_<hash>``: readable, and distinct for distinct schedules.

    The slug alone drops non-ASCII text and is cut at 60 characters, so "Go right" and
    "Go right 🚀" (or two long instructions with the same start) would share a folder and
    overwrite each other's reports; the hash of the full schedule keeps them apart.
    """
    digest = hashlib.sha256(json.dumps(instructions, ensure_ascii=False).encode()).hexdigest()[:8]
    return "_".join(
        part for part in ("instruct", slug("_".join(instructions))[:60], digest) if part
    )


@contextmanager
def _llm_errors():
    """An unreachable model as a ValueError, which ``clean_errors`` reports in one line."""
    try:
        yield
    except LLMUnavailable as err:
        raise ValueError(str(err)) from None


def run_instruct(cfg: DictConfig, run_dir: str | Path, instruction: str) -> float:
    """The mean episode team reward of the first method (see the module doc)."""
    with clean_errors("instruct"), _llm_errors():
        instructions = split_instructions(instruction)
        field_size = float(cfg.env.params.field_size)
        planner = LLMPlanner.from_config(cfg.llm, field_size=field_size)
        # The offline rule planner is deterministic: if it declines an instruction it never
        # understands it, so say so now (naming it) rather than run on fallback waypoints.
        offline = is_offline(planner.model)
        if offline:
            check_understood(instructions, field_size / 2)
            for text in instructions:
                print(how_read(text, field_size / 2), flush=True)
        paths = find_checkpoints(cfg)
        name = out_dir_name(instructions)
        out_dir = results_dir(cfg.eval.out_dir, paths, name)
        title = (
            f"Language instructions via {planner.model} ({planner.prompt} prompt): "
            + " -> ".join(f'"{text}"' for text in instructions)
        )
        result = evaluate_checkpoints(
            cfg,
            paths,
            lambda episode: language_schedule(
                planner,
                instructions,
                cfg.eval.steps,
                strict=offline,
                plan=cfg.eval.plan,
            ),
            gif_stem=out_dir / "instruct" if cfg.eval.gif else None,
            label_suffix=methods.TAP if planner.prompt == "tap" else "",
        )
        return write_report(
            result,
            cfg,
            name="instruct",
            out_dir=out_dir,
            title=title,
            meta=dict(
                llm_backend=cfg.llm.backend,
                model=planner.model,
                prompt=planner.prompt,
                instructions=instructions,
                plan=cfg.eval.plan,
            ),
        )


def prepare_instruct(command: str, args: list[str]) -> tuple[list[str], dict]:
    """The instruction text comes first, then the overrides; it reaches :func:`run_instruct` as
    an option of the command."""
    if not args or "=" in args[0] or args[0].startswith("-"):
        raise ValueError(
            'give the instruction first, e.g. icco instruct "Go right" checkpoint=PATH'
        )
    overrides, options = results_beside_checkpoint(command, args[1:])
    return overrides, {**options, "instruction": args[0]}


INSTRUCT = Command(run=run_instruct, prepare=prepare_instruct)

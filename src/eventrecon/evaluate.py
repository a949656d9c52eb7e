"""Held-out evaluation: render the validation views at every ground-truth time.

``python -m eventrecon.evaluate run=DIR [ckpt=last|best] [color_correct=MODE]`` loads a
finished or interrupted run (its ``.hydra/config.yaml`` and per-segment checkpoints),
renders every held-out view at every ground-truth time (cross-fading segments inside
their overlaps), writes ``renders/<view>/<frame:04d>.png`` and an animated GIF per view
(render | ground truth), and saves ``metrics_eval.json`` (PSNR, SSIM, LPIPS on the
sRGB-encoded images, as the published PNGs are compared). ``color_correct=per_image`` or
``eventnerf`` (EventNeRF's joint fit; ``true`` is ``per_image``) scores the colour-corrected
renders instead and writes ``metrics_eval_<MODE>.json``.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from eventrecon.common.errors import InputError
from eventrecon.engine.run_folder import evaluate_run
from eventrecon.evaluation.metrics import CORRECTIONS

__all__ = ["main"]

log = logging.getLogger(__name__)


USAGE = ("usage: python -m eventrecon.evaluate run=DIR [ckpt=last|best] "
         "[color_correct=none|per_image|eventnerf]")


def main(argv: Sequence[str] | None = None) -> int:
    """CLI (see module docstring). Exit 0 done, 2 bad input (one line)."""
    argv = list(argv if argv is not None else sys.argv[1:])
    known = {"run", "ckpt", "color_correct"}
    bad = [a for a in argv if "=" not in a or a.split("=", 1)[0] not in known]
    args = dict(a.split("=", 1) for a in argv if a not in bad)
    if bad or "run" not in args:
        log.error("%s (got %s)", USAGE, " ".join(argv) or "nothing")
        return 2
    if args.get("ckpt", "last") not in ("last", "best"):
        log.error("ckpt: expected last or best, got %s", args["ckpt"])
        return 2
    colour = args.get("color_correct", "none").lower()
    colour = {"true": "per_image", "false": "none"}.get(colour, colour)
    if colour not in CORRECTIONS:
        log.error("color_correct: expected one of %s, got %s", ", ".join(CORRECTIONS),
                  args["color_correct"])
        return 2
    try:
        metrics = evaluate_run(Path(args["run"]), ckpt=args.get("ckpt", "last"),
                               color_correct=colour)
    except InputError as e:
        log.error("%s", e)
        return 2
    log.info("%s", json.dumps(metrics, indent=1))
    return 0


if __name__ == "__main__":
    from eventrecon.common.malloc import retain_freed_memory

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    retain_freed_memory()
    raise SystemExit(main())

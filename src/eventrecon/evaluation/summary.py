"""The short table a run ends with: its scores, whether it learnt anything, its cost, and
where to look next.

>>> m = {"scene": "spheres", "model": "nerf", "loss": "full", "seed": 0, "status": "ok",
...      "psnr": 24.86, "ssim": 0.873, "lpips": 0.1234, "lpips_vgg": None,
...      "lpips_vgg_note": "no VGG16 weights",
...      "psnr_background": 21.42, "steps": 2500, "wall_s": 270.0, "sec_per_it": 0.108,
...      "total_s": 333.0, "peak_mem_mb": 1200.0}
>>> print(format_summary(m, "outputs/run"))  # doctest: +NORMALIZE_WHITESPACE
run summary — spheres · nerf · full · seed 0
  held-out PSNR   24.86 dB   (empty field 21.42 dB: +3.44 dB)
  SSIM            0.8730
  LPIPS-Alex      0.1234
  LPIPS-VGG       n/a (no VGG16 weights)
  status          ok
  training        2500 steps in 4m30s (0.108 s/it); 5m33s in all
  peak memory     1.2 GB
  run folder      outputs/run
  renders, GIFs   outputs/run/renders/
  TensorBoard     make tensorboard  (or: tensorboard --logdir outputs/run)
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from eventrecon.common.progress import format_seconds

__all__ = ["format_summary"]


def _num(value: Any, fmt: str) -> str:
    return format(value, fmt) if isinstance(value, (int, float)) else "—"


def format_summary(metrics: Mapping[str, Any], out_dir: str | Path) -> str:
    """The end-of-run table (module docstring) of a run's ``metrics.json`` contents."""
    out = Path(out_dir)
    title = " · ".join(str(metrics.get(k)) for k in ("scene", "model", "loss")
                       if metrics.get(k) is not None)
    if metrics.get("seed") is not None:
        title += f" · seed {metrics['seed']}"
    psnr, empty = metrics.get("psnr"), metrics.get("psnr_background")
    gain = ""
    if isinstance(psnr, (int, float)) and isinstance(empty, (int, float)):
        gain = f"   (empty field {empty:.2f} dB: {psnr - empty:+.2f} dB)"
    lp = {key: _num(metrics[key], ".4f") if metrics.get(key) is not None
          else f"n/a ({metrics.get(key + '_note')})" for key in ("lpips", "lpips_vgg")}
    status = str(metrics.get("status"))
    if status == "collapsed":
        status = f"COLLAPSED — renders the empty field ({metrics.get('collapse_reason')})"
    mem = metrics.get("peak_mem_mb")
    changed = ["schedules compressed" if metrics.get("schedule") == "compressed" else "",
               f"size conf/sizing/{metrics['sizing']}.yaml" if metrics.get("sizing") else "",
               "empty-space skipping" if metrics.get("skip") == "grid" else "",
               (f"lr held for the first {metrics['lr_decay_start']:.0%} of the steps, then"
                if metrics.get("lr_decay_start") else "lr")
               + f" decayed to {metrics['lr_end_factor']:g}× by the last step"
               if metrics.get("lr_end_factor") not in (None, 1.0) else "",
               "bf16 autocast" if metrics.get("precision") == "bf16-mixed" else "",
               f"lr warmed up over {metrics['lr_warmup']} steps" if metrics.get("lr_warmup")
               else "",
               f"Adam's betas to the power {metrics['betas_power']:g}"
               if metrics.get("betas_power") not in (None, 1.0) else ""]
    changed = [c for c in changed if c]
    subject = metrics.get("psnr_subject")
    rows = [
        ("held-out PSNR", f"{_num(psnr, '.2f')} dB{gain}"),
        *([("subject PSNR", f"{subject:.2f} dB   (the subject's pixels; gain over empty "
                            f"{metrics.get('gain_psnr_subject', float('nan')):+.2f} dB)")]
          if isinstance(subject, (int, float)) else []),
        ("SSIM", _num(metrics.get("ssim"), ".4f")),
        ("LPIPS-Alex", lp["lpips"]),
        ("LPIPS-VGG", lp["lpips_vgg"]),
        ("status", status),
        ("training", f"{metrics.get('steps')} steps in "
                     f"{format_seconds(float(metrics.get('wall_s') or 0))} "
                     f"({_num(metrics.get('sec_per_it'), '.3f')} s/it); "
                     f"{format_seconds(float(metrics.get('total_s') or 0))} in all"),
        ("peak memory", f"{mem / 1000:.1f} GB" if isinstance(mem, (int, float)) else "—"),
        *([("CPU choices", "; ".join(changed) + "  (the paper's method otherwise)")]
          if changed else []),
        ("run folder", str(out)),
        ("renders, GIFs", f"{out / 'renders'}/"),
        ("TensorBoard", f"make tensorboard  (or: tensorboard --logdir {out})"),
    ]
    return "\n".join([f"run summary — {title}"] + [f"  {k:<15} {v}" for k, v in rows])

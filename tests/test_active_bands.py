"""The NeRF's first layer without the columns of bands that are off (grad mode off)."""

from __future__ import annotations

import pytest
import torch

from eventrecon.errors import InputError
from eventrecon.fields import NeRFField
from eventrecon.fields.encoding import active_columns, encode_active, encode_grouped

# training steps of a 4000-step annealing: every band off; the first of each partly on;
# two position bands on and a time band partly on; all but a partial last band on
STEPS = [0, 300, 1200, 3990]


def _field(skip: int, depth: int = 4) -> NeRFField:
    torch.manual_seed(7)
    return NeRFField(depth=depth, width=32, skip=skip, pos_bands=5, time_bands=3,
                     remap_width=32, colour_width=16, anneal_steps=4000)


def _weights(f: NeRFField) -> list[float]:
    return [w for e in (f.pos_enc, f.time_enc) for w in e.weights for _ in range(e.in_dim)]


@pytest.mark.parametrize("dtype", [None, torch.bfloat16])
@pytest.mark.parametrize("step", STEPS)
def test_active_columns_are_the_grouped_features_that_are_not_zero(step, dtype) -> None:
    """``encode_active`` is ``encode_grouped``'s output at the kept columns, to the bit;
    every column it leaves out is zero for every input, and it keeps ``4 + 2k`` for ``k``
    angle columns of non-zero weight."""
    f = _field(-1)
    f.set_progress(step)
    weights = _weights(f)
    x = torch.cat([torch.rand(257, 3) * 4 - 2, torch.rand(257, 1)], dim=-1)
    full = encode_grouped(x, f.feature_freqs, f.pos_enc.window.new_tensor(weights),
                          dtype, weights)
    active = active_columns(f.feature_freqs, weights)
    k = sum(w != 0.0 for w in weights)
    assert active.columns.numel() == 4 + 2 * k
    assert torch.equal(encode_active(x, active, dtype), full[:, active.columns])
    left_out = sorted(set(range(full.shape[1])) - set(active.columns.tolist()))
    assert len(left_out) == full.shape[1] - 4 - 2 * k
    assert not full[:, left_out].any()


@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("depth, skip", [(4, -1), (4, 1), (8, 4)])
@pytest.mark.parametrize("step", STEPS)
def test_the_field_without_grad_reads_only_the_kept_columns(step, depth, skip, autocast,
                                                            monkeypatch) -> None:
    """With grad mode off and some bands off the trunk reads ``4 + 2k`` feature columns
    (without the skip, and with it after layer 1 or, as the paper's network, layer 4);
    σ and rgb equal those of the full layout up to the rounding of sums in another order
    (fp32: 1e-5; bf16 autocast: its 8-bit mantissa)."""
    f = _field(skip, depth)
    f.set_progress(step)
    k = sum(w != 0.0 for w in _weights(f))
    xyz, t = torch.rand(1025, 3) * 2 - 1, torch.rand(1025, 1)
    widths: list[int] = []

    def recorded(i: int, columns: torch.Tensor | None = None) -> torch.Tensor:
        weight = NeRFField.layer_weight(f, i, columns)
        widths.append(weight.shape[1])
        return weight
    monkeypatch.setattr(f, "layer_weight", recorded)
    full_width = 4 + 2 * 5 * 3 + 2 * 3
    with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=autocast):
        kept = f(xyz, t)
        assert widths[0] == 4 + 2 * k and (skip < 0 or widths[skip + 1] == 4 + 2 * k + 32)
        widths.clear()
        monkeypatch.setattr(f, "active_features", lambda *_: None)
        full = f(xyz, t)
        assert widths[0] == full_width and (skip < 0 or widths[skip + 1] == full_width + 32)
    tol = 3e-2 if autocast else 1e-5
    for a, b in zip(kept, full):
        assert a.dtype == b.dtype
        assert torch.allclose(a.float(), b.float(), rtol=tol, atol=tol * b.float().abs().max())
    assert float(kept[0].float().std()) > 0


def test_the_kept_columns_follow_the_window_and_grad_mode() -> None:
    """The layout is rebuilt when the window changes (and then reused); with grad mode on,
    or every band on, the full layout is read."""
    f = _field(-1)
    xyz, t = torch.rand(9, 3), torch.rand(9, 1)
    with torch.no_grad():
        f.set_progress(300)
        first = f.active_features(xyz, t)[1]
        assert f.active_features(xyz, t)[1] is first
        f.set_progress(1200)
        later = f.active_features(xyz, t)[1]
        assert later is not first and later.columns.numel() > first.columns.numel()
        f.set_progress(4000)
        assert f.active_features(xyz, t) is None
        g = _field(-1)                           # a checkpoint of another window, loaded
        g.set_progress(300)
        f.set_progress(1200)
        f.active_features(xyz, t)
        f.load_state_dict(g.state_dict())
        assert torch.equal(f.active_features(xyz, t)[1].columns, first.columns)
        assert torch.equal(f.active_features(xyz, t)[0],
                           f.features(xyz, t)[:, first.columns])
    f.set_progress(300)
    assert f.active_features(xyz, t) is None                 # grad mode on: training


def test_active_columns_refuse_weights_of_the_wrong_length() -> None:
    f = _field(-1)
    with pytest.raises(InputError, match="weights"):
        active_columns(f.feature_freqs, [1.0] * 3)

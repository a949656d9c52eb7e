"""LPIPS (AlexNet, v0.1) built without torchvision.

The learned perceptual distance of Zhang et al. (2018) between two images ``x0, x1``
given in ``[-1, 1]``:

.. math::

    d(x_0, x_1) = \\sum_{l=1}^{5} \\frac{1}{H_l W_l} \\sum_{h,w}
                  \\sum_c w_{l,c}\\,\\big(\\hat f^l_{hwc}(x_0) - \\hat f^l_{hwc}(x_1)\\big)^2,

where ``f^l`` is the AlexNet activation after ``relu_l`` of the input scaled by
``(x - shift) / scale`` (shift = (-.030, -.088, -.188), scale = (.458, .448, .450)),
``\\hat f = f / (||f||_2 over channels + 1e-10)`` and ``w_l`` are the linear heads
(1x1 convolutions without bias) of the ``lpips`` package's ``weights/v0.1/alex.pth``.

The trunk is :class:`AlexNetTrunk`, whose ``state_dict`` keys are exactly torchvision's
``alexnet().features`` keys (``features.0.weight`` ... ``features.10.bias``), so the
ImageNet checkpoint ``alexnet-owt-7be5be79.pth`` loads directly. Weights come from, in
order: ``$EVENTRECON_ALEXNET_WEIGHTS``; the torch hub cache
(``$TORCH_HOME/hub/checkpoints``); a download through
:func:`torch.hub.load_state_dict_from_url` (skipped when ``EVENTRECON_OFFLINE=1`` or
``CI`` is set, and attempted only after a 5 s reachability probe). When none works,
:func:`load_lpips_alex` raises :class:`LPIPSUnavailable` with a one-line reason.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import urllib.request
from pathlib import Path

import torch
from torch import nn

log = logging.getLogger(__name__)

ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
ALEXNET_FILE = ALEXNET_URL.rsplit("/", 1)[-1]
#: Environment variable naming a local AlexNet checkpoint (torchvision key layout).
WEIGHTS_ENV = "EVENTRECON_ALEXNET_WEIGHTS"
#: Environment variable that forbids any download attempt.
OFFLINE_ENV = "EVENTRECON_OFFLINE"
#: Channels at the five LPIPS taps (relu1..relu5).
ALEX_CHANNELS: tuple[int, ...] = (64, 192, 384, 256, 256)
#: Index (in ``features``) of the ReLU closing each LPIPS tap.
ALEX_TAPS: tuple[int, ...] = (1, 4, 7, 9, 11)
LPIPS_SHIFT: tuple[float, float, float] = (-0.030, -0.088, -0.188)
LPIPS_SCALE: tuple[float, float, float] = (0.458, 0.448, 0.450)


class LPIPSUnavailable(RuntimeError):
    """The AlexNet trunk or the linear heads cannot be had; ``str(e)`` is one line."""


class AlexNetTrunk(nn.Module):
    """AlexNet's convolutional ``features`` with torchvision's layer indices.

    ``features``: 0 conv 3→64 k11 s4 p2, 1 ReLU, 2 maxpool 3/2, 3 conv 64→192 k5 p2,
    4 ReLU, 5 maxpool, 6 conv 192→384 k3 p1, 7 ReLU, 8 conv 384→256 k3 p1, 9 ReLU,
    10 conv 256→256 k3 p1, 11 ReLU, 12 maxpool (unused by LPIPS).

    ``forward(x [B,3,H,W]) -> list`` of the five activations after relu1..relu5,
    ``[B,C_l,H_l,W_l]`` with ``C = (64, 192, 384, 256, 256)``.

    >>> sorted(AlexNetTrunk().state_dict())[:2]
    ['features.0.bias', 'features.0.weight']
    >>> [f.shape[1] for f in AlexNetTrunk()(torch.zeros(1, 3, 64, 64))]
    [64, 192, 384, 256, 256]
    """

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(64, 192, kernel_size=5, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(192, 384, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(384, 256, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(256, 256, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in ALEX_TAPS:
                taps.append(x)
                if len(taps) == len(ALEX_TAPS):
                    break
        return taps


def _unit_normalize(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """``f / (sqrt(sum_c f²) + eps)`` over the channel axis of ``[B,C,H,W]``."""
    return f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + eps)


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 with the AlexNet trunk (see the module docstring for the maths).

    ``forward(x0 [B,3,H,W], x1 [B,3,H,W]) -> [B]``, inputs in ``[-1, 1]``.
    The linear heads are buffers ``lin0 .. lin4`` of shape ``[C_l]`` (non-negative in
    the published weights); the trunk is :class:`AlexNetTrunk` in ``self.net``.

    >>> m = LPIPSAlex()  # random trunk, zero heads until loaded
    >>> x = torch.rand(2, 3, 64, 64) * 2 - 1
    >>> float(m(x, x).abs().max())
    0.0
    """

    def __init__(self) -> None:
        super().__init__()
        self.net = AlexNetTrunk()
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))
        for k, c in enumerate(ALEX_CHANNELS):
            self.register_buffer(f"lin{k}", torch.zeros(c))
        self.requires_grad_(False)
        self.eval()

    def load_heads(self, state: dict[str, torch.Tensor]) -> None:
        """Load the heads from an lpips weight dict (``lin{k}.model.1.weight``: ``[1,C,1,1]``)."""
        for k, c in enumerate(ALEX_CHANNELS):
            key = f"lin{k}.model.1.weight"
            if key not in state or state[key].numel() != c:
                raise LPIPSUnavailable(f"LPIPS linear weights: missing or malformed {key}")
            getattr(self, f"lin{k}").copy_(state[key].reshape(c))

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        f0 = self.net((x0 - self.shift) / self.scale)
        f1 = self.net((x1 - self.shift) / self.scale)
        total = x0.new_zeros(x0.shape[0])
        for k, (a, b) in enumerate(zip(f0, f1)):
            diff = (_unit_normalize(a) - _unit_normalize(b)) ** 2  # [B,C,H,W]
            w = getattr(self, f"lin{k}")
            total = total + torch.einsum("bchw,c->bhw", diff, w).mean(dim=(1, 2))
        return total


def lpips_heads_path() -> Path:
    """Path of ``lpips/weights/v0.1/alex.pth`` in the installed ``lpips`` package.

    Found with :func:`importlib.util.find_spec` (the package is not imported: it
    imports torchvision). Raises :class:`LPIPSUnavailable` when absent.
    """
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSUnavailable("LPIPS linear weights: the lpips package is not installed")
    for loc in spec.submodule_search_locations:
        path = Path(loc) / "weights" / "v0.1" / "alex.pth"
        if path.is_file():
            return path
    raise LPIPSUnavailable("LPIPS linear weights: lpips/weights/v0.1/alex.pth not found")


def _offline() -> bool:
    flag = os.environ.get(OFFLINE_ENV, "").strip().lower()
    return flag not in ("", "0", "false", "no") or bool(os.environ.get("CI"))


def _reachable(url: str, timeout_s: float) -> str | None:
    """``None`` if ``url`` answers a HEAD request within ``timeout_s``, else the reason."""
    try:
        req = urllib.request.Request(url, method="HEAD")
        with urllib.request.urlopen(req, timeout=timeout_s):  # noqa: S310 (fixed https URL)
            return None
    except Exception as exc:  # noqa: BLE001 (any network failure means "unavailable")
        return f"{type(exc).__name__}: {exc}".replace("\n", " ")


def _trunk_state(path_or_state: Path | dict) -> dict[str, torch.Tensor]:
    state = (
        torch.load(path_or_state, map_location="cpu", weights_only=True)
        if isinstance(path_or_state, Path)
        else path_or_state
    )
    feats = {k: v for k, v in state.items() if k.startswith("features.")}
    if not feats:
        raise LPIPSUnavailable("AlexNet weights: no 'features.*' keys in the checkpoint")
    return feats


def alexnet_trunk_weights(probe_timeout_s: float = 5.0) -> dict[str, torch.Tensor]:
    """ImageNet AlexNet ``features.*`` weights, or :class:`LPIPSUnavailable`.

    Order: ``$EVENTRECON_ALEXNET_WEIGHTS``; ``<torch.hub.get_dir()>/checkpoints/
    alexnet-owt-7be5be79.pth``; download (not when offline; after a HEAD probe with
    ``probe_timeout_s`` so that no network means a fast failure).
    """
    env_path = os.environ.get(WEIGHTS_ENV)
    if env_path:
        path = Path(env_path)
        if not path.is_file():
            raise LPIPSUnavailable(f"AlexNet weights: ${WEIGHTS_ENV}={path} is not a file")
        return _trunk_state(path)
    cached = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE
    if cached.is_file():
        return _trunk_state(cached)
    if _offline():
        raise LPIPSUnavailable(
            f"AlexNet weights not in {cached.parent} and downloads are off "
            f"({OFFLINE_ENV}/CI set); set ${WEIGHTS_ENV} or fill the torch hub cache"
        )
    reason = _reachable(ALEXNET_URL, probe_timeout_s)
    if reason is not None:
        raise LPIPSUnavailable(
            f"AlexNet weights not in {cached.parent} and {ALEXNET_URL} unreachable ({reason})"
        )
    try:
        state = torch.hub.load_state_dict_from_url(
            ALEXNET_URL, map_location="cpu", progress=False, check_hash=True
        )
    except Exception as exc:  # noqa: BLE001
        raise LPIPSUnavailable(f"AlexNet weights download failed: {type(exc).__name__}") from exc
    return _trunk_state(state)


_CACHE: dict[tuple, LPIPSAlex | LPIPSUnavailable] = {}


def load_lpips_alex(device: torch.device | str = "cpu") -> LPIPSAlex:
    """The pretrained LPIPS-Alex network on ``device`` (built once per weight source).

    Raises :class:`LPIPSUnavailable` (one-line message) when weights cannot be had;
    the failure is remembered too, so a missing network costs one probe per process.
    """
    key = (
        os.environ.get(WEIGHTS_ENV),
        torch.hub.get_dir(),
        _offline(),
        str(torch.device(device)),
    )
    if key not in _CACHE:
        try:
            model = LPIPSAlex()
            model.load_heads(torch.load(lpips_heads_path(), map_location="cpu", weights_only=True))
            model.net.load_state_dict(alexnet_trunk_weights())
            _CACHE[key] = model.to(device)
        except LPIPSUnavailable as exc:
            _CACHE[key] = exc
    entry = _CACHE[key]
    if isinstance(entry, LPIPSUnavailable):
        raise entry
    return entry

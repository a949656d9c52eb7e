"""Compiled CPU kernels (numba), each the second implementation of one operation whose
readable PyTorch reference lives with its backbone, and the one switch between them.

- NGP's 4D hash encoding, forward and table gradient: reference
  :meth:`baselines.ngp.HashEncoding.forward` (vectorised corners + ``embedding_bag``),
  kernel :func:`.hash_grid.encode`;
- TensoRF-CP's rank sum of four line products, forward and line gradients: reference
  :meth:`baselines.factorised.FactorisedField.rank_sum` (``grid_sample`` per line),
  kernel :func:`.factor_grids.cp_rank_sum`;
- HexPlane's rank sum of three plane · plane · line products, forward and factor
  gradients: the same reference, kernel :func:`.factor_grids.hex_rank_sum`.

Decorators and thread splitting: :mod:`.jit` (no compiled function of its own, no side
effect on import).

The switch is a backbone's ``implementation`` (``conf/model/*.yaml``, key
``model.implementation``):

- ``"auto"`` (default): the kernel where it applies (numba installed, CPU tensors, the
  sizes and dtypes it supports, no gradient with respect to the coordinates needed),
  else the PyTorch reference;
- ``"torch"``: the PyTorch reference everywhere (a kernel is never called);
- ``"numba"``: the kernel, and an :class:`~eventrecon.common.errors.InputError` naming
  ``implementation`` where it cannot apply.

Each kernel module has a function that says what the kernel needs and a call lacks
(``None`` where it applies: :func:`~.hash_grid.unsupported`,
:func:`~.factor_grids.cp_unsupported`, :func:`~.factor_grids.hex_unsupported`); a
backbone passes its answer to :func:`use_kernel`.
"""

from __future__ import annotations

from eventrecon.common.errors import InputError

__all__ = ["IMPLEMENTATIONS", "resolve", "use_kernel"]

#: The values of ``model.implementation``.
IMPLEMENTATIONS = ("auto", "torch", "numba")


def resolve(implementation: str) -> str:
    """``implementation`` checked against :data:`IMPLEMENTATIONS`.

    >>> resolve("auto")
    'auto'
    >>> resolve("fast")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    eventrecon.common.errors.InputError: conf/model: implementation: expected auto, torch or ...
    """
    if implementation not in IMPLEMENTATIONS:
        raise InputError("conf/model", "implementation", "auto, torch or numba",
                         implementation)
    return implementation


def use_kernel(implementation: str, missing: str | None) -> bool:
    """Whether a call runs the kernel: ``implementation`` (:func:`resolve`d) and what the
    kernel needs and this call lacks (``None``: nothing, it applies).

    >>> use_kernel("auto", None), use_kernel("auto", "a CPU"), use_kernel("torch", None)
    (True, False, False)
    >>> use_kernel("numba", "a CPU")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    eventrecon.common.errors.InputError: conf/model: implementation: expected auto or torch ...

    Raises:
        InputError: ``implementation`` is ``"numba"`` and ``missing`` names a reason, or
            ``implementation`` is not one of :data:`IMPLEMENTATIONS`.
    """
    if resolve(implementation) == "torch":
        return False
    if missing is None:
        return True
    if implementation == "numba":
        raise InputError("conf/model", "implementation",
                         f"auto or torch where the numba kernel does not apply (it needs "
                         f"{missing})", implementation)
    return False

"""The backbone zoo: NGP (4D hash grid), TensoRF-CP 4D and HexPlane as drop-in Fields.

Each backbone is a :class:`eventrecon.fields.base.Field` with its own schedule
(``callbacks()``): cylinder annealing for NGP, grid growth for the factorised ones.
Select one with ``python train.py model=ngp|tensorf_cp|hexplane``.
"""

from baselines.hexplane import HexPlaneField
from baselines.ngp import HashEncoding, NGPField, hash_encode_reference
from baselines.schedules import CylinderAnneal, GridGrowth, GrowthPlan
from baselines.tensorf_cp import TensoRFCPField

__all__ = [
    "CylinderAnneal",
    "GridGrowth",
    "GrowthPlan",
    "HashEncoding",
    "HexPlaneField",
    "NGPField",
    "TensoRFCPField",
    "hash_encode_reference",
]

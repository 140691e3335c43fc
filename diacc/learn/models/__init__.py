"""Actor and critic networks of every variant (MAPPO, MAPPO-IADM, DIACC).

Entry points: :func:`build_networks` pairs networks per variant and
:func:`to_tensors` turns observation containers into the tensor dicts they take.
"""

from diacc.learn.models.errors import ModelError
from diacc.learn.models.inputs import merge_leading, to_tensors
from diacc.learn.models.recurrent import RecurrentNet
from diacc.learn.models.registry import build_networks, parameter_count

__all__ = [
    "ModelError",
    "RecurrentNet",
    "build_networks",
    "merge_leading",
    "parameter_count",
    "to_tensors",
]

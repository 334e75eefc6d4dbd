"""CSNet-L-x1 salient-object detection, and the `saliency` criterion built on it.

The network is CSNet (Gao, Tan, Cheng, Lu, Chen and Yan, "Highly Efficient Salient Object Detection
with 100K Parameters", ECCV 2020), in its published CSNet-L-x1 variant (97,921 parameters counting
the batch-norm running statistics): a port of the architecture and a converter for the authors'
weights, written from the paper and the facts of the reference implementation
(github.com/ShangHua-Gao/SOD100K, `CSNet/model/`), none of it copied.

Licence: the weights are the authors' release under CC BY-NC-SA 4.0 (non-commercial). They are read
from the weights folder (`--weights`, `WALDO_WEIGHTS`) and never committed to this repository.

Modules, bottom to top: `config` (the architecture from the `.bin` channel splits), `model` (the
Flax layers and network), `convert` (torch weights -> Flax variables, the registered converter),
`criterion` (parameters, saliency maps, the `saliency` criterion). This face re-exports their
public names. The architecture in words: docs/design.md, "Criteria".
"""

from waldo_jax.criteria.csnet.config import BlockSpec as BlockSpec
from waldo_jax.criteria.csnet.config import CSNetConfig as CSNetConfig
from waldo_jax.criteria.csnet.config import Splits as Splits
from waldo_jax.criteria.csnet.convert import FILES as FILES
from waldo_jax.criteria.csnet.convert import MODEL as MODEL
from waldo_jax.criteria.csnet.convert import convert_state_dict as convert_state_dict
from waldo_jax.criteria.csnet.convert import flax_shapes as flax_shapes
from waldo_jax.criteria.csnet.convert import read as read
from waldo_jax.criteria.csnet.convert import read_layer_config as read_layer_config
from waldo_jax.criteria.csnet.convert import torch_shapes as torch_shapes
from waldo_jax.criteria.csnet.criterion import INPUT_SIZE as INPUT_SIZE
from waldo_jax.criteria.csnet.criterion import SALIENT_THRESHOLD as SALIENT_THRESHOLD
from waldo_jax.criteria.csnet.criterion import SOFTNESS as SOFTNESS
from waldo_jax.criteria.csnet.criterion import CSNetParams as CSNetParams
from waldo_jax.criteria.csnet.criterion import load_params as load_params
from waldo_jax.criteria.csnet.criterion import saliency as saliency
from waldo_jax.criteria.csnet.criterion import saliency_map as saliency_map
from waldo_jax.criteria.csnet.criterion import saliency_maps as saliency_maps
from waldo_jax.criteria.csnet.criterion import salient_fraction as salient_fraction
from waldo_jax.criteria.csnet.criterion import soft_salient_fraction as soft_salient_fraction
from waldo_jax.criteria.csnet.model import CSFHead as CSFHead
from waldo_jax.criteria.csnet.model import CSNet as CSNet
from waldo_jax.criteria.csnet.model import DepthwiseCBR as DepthwiseCBR
from waldo_jax.criteria.csnet.model import GOctaveCBR as GOctaveCBR
from waldo_jax.criteria.csnet.model import ILBlock as ILBlock
from waldo_jax.criteria.csnet.model import MultiScaleBlock as MultiScaleBlock

__all__ = [
    "MODEL",
    "FILES",
    "INPUT_SIZE",
    "SALIENT_THRESHOLD",
    "SOFTNESS",
    "BlockSpec",
    "CSNetConfig",
    "GOctaveCBR",
    "DepthwiseCBR",
    "MultiScaleBlock",
    "ILBlock",
    "CSFHead",
    "CSNet",
    "CSNetParams",
    "torch_shapes",
    "flax_shapes",
    "convert_state_dict",
    "read_layer_config",
    "read",
    "load_params",
    "saliency_map",
    "saliency_maps",
    "salient_fraction",
    "soft_salient_fraction",
    "saliency",
]

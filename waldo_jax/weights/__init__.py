"""Criterion weights: reading torch pickles without torch and OpenCV YAML without OpenCV, the native
`.npz` format, the weights folder.

See `waldo_jax.weights.store` for the folder layout and `waldo weights convert`.
"""

from waldo_jax.weights.opencv_yaml import read_opencv_storage as read_opencv_storage
from waldo_jax.weights.store import CONVERTERS as CONVERTERS
from waldo_jax.weights.store import Converter as Converter
from waldo_jax.weights.store import WeightsError as WeightsError
from waldo_jax.weights.store import check_shapes as check_shapes
from waldo_jax.weights.store import convert_all as convert_all
from waldo_jax.weights.store import load_model as load_model
from waldo_jax.weights.store import load_native as load_native
from waldo_jax.weights.store import register_converter as register_converter
from waldo_jax.weights.store import resolve_weights_dir as resolve_weights_dir
from waldo_jax.weights.store import save_native as save_native
from waldo_jax.weights.store import weights_file as weights_file
from waldo_jax.weights.torch_pickle import TorchPickleError as TorchPickleError
from waldo_jax.weights.torch_pickle import read_torch_file as read_torch_file
from waldo_jax.weights.torch_pickle import state_dict as state_dict

"""The static architecture of a (pruned) CSNet, as set by the channel splits of its `.bin`.

Feature maps are lists of *branches*: branch `j` holds `c_j` channels at 1 / 2**j of the block's
resolution (a generalised octave, gOctConv). The paper's pruning chose every layer's `c_j`; the
`.bin` stores them (for CSNet-L-x1, 22 entries: 18 blocks, 3 head layers, the stage lengths
`(3, 4, 6, 4)`). `CSNetConfig` parses and checks it; the layers (`model`) and the converter
(`convert`) are built from it.

Names: `splits` are per-branch channel counts (a tuple of ints per layer).
"""

from __future__ import annotations

import dataclasses
from typing import Any, List, NamedTuple, Sequence, Tuple

import numpy as np

from waldo_jax.weights import WeightsError

__all__ = ["Splits", "DILATIONS", "BlockSpec", "CSNetConfig"]

Splits = Tuple[int, ...]
"""Channels of each branch of one layer, branch 0 (full resolution) first."""

DILATIONS = (1, 2, 4, 8, 16)  # the dilations of the head's multi-scale block
_NUM_STAGES = 4  # stages 1..4 after stage 0


@dataclasses.dataclass(frozen=True)
class BlockSpec:
    """One ILBlock: its torch prefix (e.g. "stage2.0"), Flax name, splits, first conv's kernel and stride."""

    torch_prefix: str
    name: str
    in_splits: Splits
    out_splits: Splits
    kernel_size: int
    stride: int


@dataclasses.dataclass(frozen=True)
class CSNetConfig:
    """The static architecture of a (pruned) CSNet, from its `.bin` layer config. Hashable.

    Attributes:
      blocks: (in_splits, out_splits) of each ILBlock, stage 0 then stages 1-4 in order.
      stages: blocks in stages 1-4, e.g. (3, 4, 6, 4).
      fuse_in: channels of the three stage outputs the head takes (stages 2, 3, 4).
      fuse_mid: out splits of the head's first gOctave 1x1 conv (= the multi-scale blocks' inputs).
      fuse_ms: out channels of the multi-scale block of each head branch.
      fuse_dilations: per head branch, out channels of the convs with dilations 1, 2, 4, 8, 16
        (0: that conv is absent).
      fuse_out: channels of the head's output (its final gOctave 1x1 conv, one branch).
    """

    blocks: Tuple[Tuple[Splits, Splits], ...]
    stages: Tuple[int, ...]
    fuse_in: Splits
    fuse_mid: Splits
    fuse_ms: Splits
    fuse_dilations: Tuple[Splits, ...]
    fuse_out: int

    def block_specs(self) -> Tuple[BlockSpec, ...]:
        """The ILBlocks in order, with the stride and first-conv kernel the reference gives each."""
        specs = [BlockSpec("stage0.0", "stage0_0", *self.blocks[0], kernel_size=3, stride=1)]
        index = 1
        for stage, length in enumerate(self.stages, start=1):
            for k in range(length):
                stride = 2 if (stage >= 2 and k == 0) else 1
                kernel = 3 if stride == 2 else 1
                specs.append(
                    BlockSpec(
                        f"stage{stage}.{k}", f"stage{stage}_{k}", *self.blocks[index], kernel_size=kernel, stride=stride
                    )
                )
                index += 1
        return tuple(specs)

    def stage_ends(self) -> Tuple[int, int, int]:
        """Indices (into `block_specs()`) of the last blocks of stages 2, 3, 4 (the head's inputs)."""
        ends = np.cumsum((1,) + self.stages) - 1  # last block index of stage 0, 1, 2, 3, 4
        return int(ends[2]), int(ends[3]), int(ends[4])

    def to_layer_config(self) -> List[Any]:
        """The `.bin` layer config as JSON-able nested int lists (the converter's `meta`)."""
        layers: List[Any] = [[list(i), list(o)] for i, o in self.blocks]
        layers.append([list(self.fuse_in), list(self.fuse_mid)])
        layers.append([list(self.fuse_mid), list(self.fuse_ms), [list(d) for d in self.fuse_dilations]])
        layers.append([list(self.fuse_ms), [self.fuse_out]])
        layers.append(list(self.stages))
        return layers

    @classmethod
    def from_layer_config(cls, layer_config: Sequence[Any], source: str = "layer config") -> "CSNetConfig":
        """Parses and checks a `.bin` layer config (NumPy arrays or nested lists, as in `to_layer_config`).

        Raises:
          WeightsError: naming `source` and the first entry that does not describe a CSNet.
        """
        try:
            layers = list(layer_config)
        except TypeError:
            raise WeightsError(
                f"{source}: not a CSNet layer config (a list), got {type(layer_config).__name__}"
            ) from None
        stages = _stage_lengths(layers, source)
        num_blocks = 1 + sum(stages)
        blocks = _block_splits(layers, num_blocks, source)
        head = _head_splits(layers, num_blocks, source)
        config = cls(
            blocks=blocks,
            stages=stages,
            fuse_in=head.fuse_in,
            fuse_mid=head.fuse_mid,
            fuse_ms=head.fuse_ms,
            fuse_dilations=head.fuse_dilations,
            fuse_out=0,
        )
        _check_head(config, head, layers, num_blocks, source)
        return dataclasses.replace(config, fuse_out=head.fuse_out[0])


# ----------------------------------------------------------------------------------------------
# Parsing a layer config (`CSNetConfig.from_layer_config`).


def _splits(value, where: str, source: str) -> Splits:
    """One layer's channel counts as ints, or a WeightsError naming `source` and `where`."""
    array = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if array.ndim != 1 or array.size == 0 or not np.all(np.isfinite(array)):
        raise WeightsError(f"{source}: {where} must be a non-empty list of channel counts, got {value!r}")
    if np.any(np.abs(array - np.round(array)) > 1e-6) or np.any(array < 0):
        raise WeightsError(f"{source}: {where} has non-integer or negative channel counts {value!r}")
    return tuple(int(round(v)) for v in array)


def _entry(layers: List[Any], index: int, size: int, source: str) -> List[Any]:
    """The `size` parts of entry `index`."""
    try:
        items = list(layers[index])
    except TypeError:
        items = []
    if len(items) != size:
        raise WeightsError(f"{source}: entry {index} must have {size} parts, got {layers[index]!r}")
    return items


def _stage_lengths(layers: List[Any], source: str) -> Tuple[int, ...]:
    """The blocks of stages 1-4 (the last entry), checked against the number of entries."""
    if len(layers) < 6:
        raise WeightsError(f"{source}: a CSNet layer config has at least 6 entries, got {len(layers)}")
    stages = _splits(layers[-1], "the last entry (blocks per stage)", source)
    if len(stages) != _NUM_STAGES or min(stages) < 1:
        raise WeightsError(f"{source}: the last entry must give {_NUM_STAGES} stage lengths >= 1, got {stages}")
    num_blocks = 1 + sum(stages)
    if len(layers) != num_blocks + 4:
        raise WeightsError(f"{source}: stages {stages} need {num_blocks + 4} entries, got {len(layers)}")
    return stages


def _block_splits(layers: List[Any], num_blocks: int, source: str) -> Tuple[Tuple[Splits, Splits], ...]:
    """(in_splits, out_splits) of each ILBlock, each block taking what the one before gives."""
    blocks = []
    for index in range(num_blocks):
        raw_in, raw_out = _entry(layers, index, 2, source)
        in_splits = (3,) if index == 0 else _splits(raw_in, f"entry {index} (in)", source)
        out_splits = _splits(raw_out, f"entry {index} (out)", source)
        if index == 0 and _splits(raw_in, "entry 0 (in)", source) != (3,):
            raise WeightsError(f"{source}: entry 0 must take the 3 RGB channels, got {raw_in!r}")
        if index > 0 and in_splits != blocks[-1][1]:
            raise WeightsError(f"{source}: entry {index} takes {in_splits} but entry {index - 1} gives {blocks[-1][1]}")
        if 0 in in_splits or 0 in out_splits:
            raise WeightsError(
                f"{source}: entry {index} has a zero-width branch ({in_splits} -> {out_splits}); "
                "this port supports only CSNets without empty branches"
            )
        blocks.append((in_splits, out_splits))
    return tuple(blocks)


class _HeadSplits(NamedTuple):
    """The head's three entries, parsed (`raw_ms_in`, `raw_out_in`: their inputs, checked by `_check_head`)."""

    fuse_in: Splits
    fuse_mid: Splits
    fuse_ms: Splits
    fuse_dilations: Tuple[Splits, ...]
    fuse_out: Splits
    raw_ms_in: Any
    raw_out_in: Any


def _head_splits(layers: List[Any], num_blocks: int, source: str) -> _HeadSplits:
    """The head's entries (after the blocks): its 1x1 conv, multi-scale block with dilations, output conv."""
    raw_fuse_in, raw_fuse_mid = _entry(layers, num_blocks, 2, source)
    raw_ms_in, raw_ms_out, raw_dils = _entry(layers, num_blocks + 1, 3, source)
    raw_out_in, raw_out = _entry(layers, num_blocks + 2, 2, source)
    fuse_in = _splits(raw_fuse_in, f"entry {num_blocks} (head in)", source)
    fuse_mid = _splits(raw_fuse_mid, f"entry {num_blocks} (head out)", source)
    fuse_ms = _splits(raw_ms_out, f"entry {num_blocks + 1} (multi-scale out)", source)
    fuse_out = _splits(raw_out, f"entry {num_blocks + 2} (head out)", source)
    try:
        dils = np.asarray(raw_dils, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        dils = np.zeros((0,))
    if dils.shape != (len(fuse_ms), len(DILATIONS)):
        raise WeightsError(
            f"{source}: entry {num_blocks + 1} needs dilation channels of shape "
            f"({len(fuse_ms)}, {len(DILATIONS)}), got {dils.shape}"
        )
    fuse_dilations = tuple(_splits(row, f"entry {num_blocks + 1} (dilations)", source) for row in dils)
    return _HeadSplits(fuse_in, fuse_mid, fuse_ms, fuse_dilations, fuse_out, raw_ms_in, raw_out_in)


def _check_head(config: CSNetConfig, head: _HeadSplits, layers: List[Any], num_blocks: int, source: str) -> None:
    """The head takes what stages 2-4 give, and its layers chain."""
    fuse_in, fuse_mid, fuse_ms = head.fuse_in, head.fuse_mid, head.fuse_ms
    stage_outs = tuple(config.blocks[i][1] for i in config.stage_ends())
    if any(len(out) != 1 for out in stage_outs) or fuse_in != tuple(out[0] for out in stage_outs):
        raise WeightsError(
            f"{source}: the head takes {fuse_in} but stages 2-4 end in branches {stage_outs} "
            "(each must be one branch of that width)"
        )
    if len(fuse_mid) != len(fuse_in) or _splits(head.raw_ms_in, f"entry {num_blocks + 1} (in)", source) != fuse_mid:
        raise WeightsError(f"{source}: the head's splits {fuse_in} -> {fuse_mid} -> {head.raw_ms_in!r} do not chain")
    if tuple(sum(d) for d in head.fuse_dilations) != fuse_ms or 0 in fuse_mid or 0 in fuse_ms:
        raise WeightsError(
            f"{source}: dilation channels {head.fuse_dilations} must sum to the non-empty multi-scale widths {fuse_ms}"
        )
    if _splits(head.raw_out_in, f"entry {num_blocks + 2} (in)", source) != fuse_ms or len(head.fuse_out) != 1:
        raise WeightsError(
            f"{source}: entry {num_blocks + 2} must map {fuse_ms} to one branch, got {layers[num_blocks + 2]!r}"
        )

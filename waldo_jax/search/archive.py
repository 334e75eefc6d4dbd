"""An archive of views by where they are seen from: the cells of MAP-Elites, and every run's coverage.

A view's descriptor is its camera centre o seen from the scene's focus f in the scene's own frame
(`views.SceneFrame`, `views.frame_axes`): the azimuth about the up axis (0 = `east`, +90 = `north`),
the elevation above the plane through f normal to up, and the distance |o - f| in units of the
training cameras' median distance r. `ViewGrid` cuts them into cells: `azimuth_cells` equal sectors
(cell 0 centred on azimuth 0), `elevation_cells` equal bands over `elevation_range` (an elevation
outside it falls in the nearest band) and distance bands cut at `distance_edges` x r. An `Archive`
keeps, per cell, the best view's fitness and its population slot (-inf and -1 when empty); a better
view replaces a cell's elite only when strictly better, so that filing views in slot order gives
the same archive as `archive_of` all at once (ties: the lowest slot). Coverage is the share of
cells filled; the QD-score the sum over filled cells of max(fitness - floor, 0), with the floor a
caller's (the worst training view in `explore`). Design: docs/design.md, "Search > MAP-Elites".
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search.views import SceneFrame, frame_axes
from waldo_jax.types import Array

__all__ = [
    "ViewGrid",
    "Archive",
    "view_descriptor",
    "view_cell",
    "archive_of",
    "merge",
    "coverage",
    "qd_score",
    "sky_map",
]

_DEGREES = 180.0 / math.pi


@dataclasses.dataclass(frozen=True)
class ViewGrid:
    """Static cells of view descriptors (hashable: part of the jit's static configuration).

    Attributes:
      azimuth_cells: A, equal sectors of 360 / A degrees about the scene's up; cell 0 is centred on
        azimuth 0 (`views.frame_axes`' east).
      elevation_cells: E, equal bands over `elevation_range`.
      elevation_range: (low, high) degrees, -90 <= low < high <= 90.
      distance_edges: increasing distances in units of the training cameras' median distance to the
        focus, cutting len(distance_edges) + 1 bands (0.75 and 1.33 by default: closer than the
        training cameras, about as far, farther).
    """

    azimuth_cells: int = 8
    elevation_cells: int = 4
    elevation_range: Tuple[float, float] = (-90.0, 90.0)
    distance_edges: Tuple[float, ...] = (0.75, 1.33)

    def __post_init__(self):
        for name in ("azimuth_cells", "elevation_cells"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 360:
                raise ValueError(f"ViewGrid.{name} must be an int in [1, 360], got {value!r}")
        low, high = (float(v) for v in self.elevation_range)
        if not -90.0 <= low < high <= 90.0:
            raise ValueError(
                f"ViewGrid.elevation_range must satisfy -90 <= low < high <= 90, got {self.elevation_range!r}"
            )
        edges = tuple(float(e) for e in self.distance_edges)
        if len(edges) > 16 or any(not math.isfinite(e) or e <= 0 for e in edges) or list(edges) != sorted(set(edges)):
            raise ValueError(
                f"ViewGrid.distance_edges must be at most 16 increasing positive numbers, got {self.distance_edges!r}"
            )
        object.__setattr__(self, "elevation_range", (low, high))
        object.__setattr__(self, "distance_edges", edges)

    @property
    def distance_bands(self) -> int:
        """D = len(distance_edges) + 1."""
        return len(self.distance_edges) + 1

    @property
    def cells(self) -> int:
        """M = A * E * D."""
        return self.azimuth_cells * self.elevation_cells * self.distance_bands

    def azimuth_centres(self) -> Tuple[float, ...]:
        """The A sectors' centre azimuths in degrees, in [-180, 180)."""
        width = 360.0 / self.azimuth_cells
        return tuple(((a * width + 180.0) % 360.0) - 180.0 or 0.0 for a in range(self.azimuth_cells))

    def elevation_bounds(self) -> Tuple[Tuple[float, float], ...]:
        """The E bands' (low, high) elevations in degrees, lowest first."""
        low, high = self.elevation_range
        step = (high - low) / self.elevation_cells
        return tuple((low + e * step, low + (e + 1) * step) for e in range(self.elevation_cells))

    def to_dict(self) -> dict:
        """The grid as JSON-ready numbers (results.json)."""
        return {
            "azimuth_cells": self.azimuth_cells,
            "elevation_cells": self.elevation_cells,
            "elevation_range": list(self.elevation_range),
            "distance_edges": list(self.distance_edges),
            "cells": self.cells,
        }


@flax.struct.dataclass
class Archive:
    """The best view of each cell.

    Attributes:
      fitness: float32 [M], the elite's signed score (higher is better); -inf where the cell is empty.
      slot: int32 [M], the elite's population slot; -1 where the cell is empty.
    """

    fitness: Array
    slot: Array

    @property
    def filled(self) -> Array:
        """bool [M], the cells that hold a view."""
        return jnp.isfinite(self.fitness)


def view_descriptor(c2w: Array, frame: SceneFrame) -> Array:
    """(azimuth degrees, elevation degrees, distance / radius) [3] of one view c2w [4, 4]."""
    east, north, up = frame_axes(frame)
    offset = c2w[:3, 3] - frame.focus
    height = jnp.dot(offset, up)
    across = jnp.hypot(jnp.dot(offset, east), jnp.dot(offset, north))
    azimuth = jnp.arctan2(jnp.dot(offset, north), jnp.dot(offset, east)) * _DEGREES
    elevation = jnp.arctan2(height, across) * _DEGREES
    return jnp.stack([azimuth, elevation, jnp.linalg.norm(offset) / frame.radius])


def view_cell(c2w: Array, frame: SceneFrame, grid: ViewGrid) -> Array:
    """The cell int32 [] of one view c2w [4, 4]: (band * E + elevation band) * A + sector; M when its
    position is not finite (outside every cell)."""
    azimuth, elevation, distance = view_descriptor(c2w, frame)
    width = 360.0 / grid.azimuth_cells
    sector = jnp.floor(jnp.mod(azimuth + 0.5 * width, 360.0) / width).astype(jnp.int32) % grid.azimuth_cells
    low, high = grid.elevation_range
    band = jnp.floor((elevation - low) / (high - low) * grid.elevation_cells).astype(jnp.int32)
    band = jnp.clip(band, 0, grid.elevation_cells - 1)
    ring = jnp.searchsorted(jnp.asarray(grid.distance_edges, jnp.float32), distance, side="right").astype(jnp.int32)
    cell = (ring * grid.elevation_cells + band) * grid.azimuth_cells + sector
    finite = jnp.all(jnp.isfinite(c2w[:3, 3])) & jnp.isfinite(distance)
    return jnp.where(finite, cell, grid.cells)


def archive_of(fitness: Array, c2w: Array, slots: Array, frame: SceneFrame, grid: ViewGrid) -> Archive:
    """The archive of a batch of views filed at once.

    Args:
      fitness: [P] signed scores (-inf or NaN: not filed).
      c2w: [P, 4, 4] the views.
      slots: int32 [P] their population slots (ties in a cell go to the lowest).
      frame: the scene frame.
      grid: the cells (static).

    Returns:
      `Archive` with [M] fields.
    """
    m = grid.cells
    fitness = jnp.asarray(fitness, jnp.float32)
    usable = jnp.isfinite(fitness)
    cells = jnp.where(usable, jax.vmap(view_cell, in_axes=(0, None, None))(c2w, frame, grid), m)  # [P]
    best = jax.ops.segment_max(jnp.where(usable, fitness, -jnp.inf), cells, num_segments=m + 1)[:m]
    is_best = usable & (fitness == best[jnp.minimum(cells, m - 1)]) & (cells < m)
    big = jnp.iinfo(jnp.int32).max
    slot = jax.ops.segment_min(jnp.where(is_best, slots.astype(jnp.int32), big), cells, num_segments=m + 1)[:m]
    filled = jnp.isfinite(best)
    return Archive(fitness=jnp.where(filled, best, -jnp.inf), slot=jnp.where(filled, slot, -1))


def merge(archive: Archive, newer: Archive) -> Archive:
    """`archive` with each cell's elite replaced where `newer`'s is strictly better (newer slots come later)."""
    better = newer.fitness > archive.fitness
    return Archive(
        fitness=jnp.where(better, newer.fitness, archive.fitness), slot=jnp.where(better, newer.slot, archive.slot)
    )


def coverage(archive: Archive) -> Array:
    """float32 [], the share of cells filled."""
    return jnp.mean(archive.filled.astype(jnp.float32))


def qd_score(archive: Archive, floor: Array) -> Array:
    """float32 [], the sum over filled cells of max(fitness - floor, 0) (`floor`: a signed fitness)."""
    gain = jnp.maximum(archive.fitness - floor, 0.0)
    return jnp.sum(jnp.where(archive.filled & jnp.isfinite(floor), gain, 0.0))


def sky_map(archive: Archive, grid: ViewGrid) -> Archive:
    """The best elite of each (elevation band, sector) over the distance bands: fields [E, A]."""
    shape = (grid.distance_bands, grid.elevation_cells, grid.azimuth_cells)
    fitness, slot = archive.fitness.reshape(shape), archive.slot.reshape(shape)
    ring = jnp.argmax(fitness, axis=0)  # the first (closest) band on ties
    pick = lambda x: jnp.take_along_axis(x, ring[None], axis=0)[0]  # noqa: E731
    return Archive(fitness=pick(fitness), slot=pick(slot))

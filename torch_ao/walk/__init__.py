"""The walk shared by every horizon and visibility-bitmask method, and the API to write a new method.

Every method of the horizon family walks the same way (the GTAO paper's Algorithm 1): per pixel, a few
screen-space directions ("slices"); along each, a few samples ("steps") on one or both sides; per
sample, the view-space offset to the centre pixel and its angle from the view vector inside the slice
plane. A method only says what it keeps per step (max horizon, falloff-weighted horizon, a bitmask,
soft sector coverage, gathered light) by subclassing :class:`SliceAccumulator`, and where the walk
goes by choosing or subclassing a :class:`SamplingPattern`.

Layers (each file one concept):

* :mod:`~torch_ao.walk.frame`: :class:`Frame` (the G-buffer flattened, channel-last) and
  :class:`Queries` (the valid pixels, the rows every tensor of the walk has).
* :mod:`~torch_ao.walk.patterns`: :class:`SlicePattern` (slice tangents, step offsets), noise, tangents.
* :mod:`~torch_ao.walk.fetch`: :class:`Footprint` (nearest, bilinear or edge-aware depth reads) and the
  hand-written backwards that keep a few floats per sample.
* :mod:`~torch_ao.walk.sample`: :class:`Sample`, what a method reads about one step.
* :mod:`~torch_ao.walk.protocol`: :class:`SamplingPattern` and :class:`SliceAccumulator`, every hook.
* :mod:`~torch_ao.walk.walk`: :func:`march` (chunks, recompute) and :class:`SliceGeometry`.

Geometry of one slice (all view space, unit vectors, shapes ``(N, 3)``):

* ``V``: from the pixel toward the camera.
* ``T``: the slice tangent, orthogonal to ``V``; side ``+1`` marches toward the screen image of ``+T``.
  (The plane through the camera spanned by ``V`` and ``T`` projects to one screen line through the
  pixel, so samples along that line lie in the slice plane.)
* ``axis = T x V``: normal of the slice plane.
* The projected normal ``n_p = N - axis (N . axis)``: as ``(V, T, axis)`` is an orthonormal frame,
  ``n_p = (N . V) V + (N . T) T``. It has length ``normal_length = |(N . V, N . T)|`` and signed angle
  ``normal_angle = atan2(N . T, N . V)`` from ``V`` (positive toward ``+T``).

A sample on side ``s`` has angle ``theta = atan2(delta . (s T), delta . V)`` from ``V``, measured toward
its own side: 0 looks at the camera, ``pi`` looks away. In signed slice coordinates it sits at
``s * theta``; the hemisphere around the projected normal spans ``[normal_angle - pi/2, normal_angle + pi/2]``.

A new method: subclass :class:`SliceAccumulator` (``begin_slice``, ``step``, ``end_slice``, ``finish``;
optionally ``begin_walk``, ``batch_steps``, ``paired_sides`` + ``step_pair``), then a module in
:mod:`torch_ao.methods` that returns it from ``accumulator(frame)`` (see ``docs/architecture.md``).
"""
from .fetch import Footprint, GradientRows, PerspectiveBilinearDepth
from .frame import Frame, Queries
from .patterns import (AZIMUTHS, BORDER_MODES, FETCH_MODES, NOISES, SLICE_SAMPLINGS, SlicePattern, hilbert_index,
                       hilbert_r2_noise, interleaved_gradient_noise, projected_normal_azimuths, staggered_offset,
                       unoccluded_slice_integral, view_basis, radius_px, step_direction, tangent_from_screen_angle, tangent_from_view_azimuth)
from .protocol import SamplingPattern, SliceAccumulator
from .sample import Sample, SampleAlong, fetch_sample
from .walk import SliceGeometry, march, march_chunks, slice_geometry

__all__ = [
    "Frame", "Queries", "SliceGeometry", "Sample", "SliceAccumulator", "SamplingPattern", "SlicePattern",
    "march", "march_chunks", "slice_geometry", "fetch_sample", "interleaved_gradient_noise",
    "hilbert_index", "hilbert_r2_noise", "projected_normal_azimuths", "staggered_offset", "unoccluded_slice_integral", "view_basis",
    "tangent_from_screen_angle", "tangent_from_view_azimuth", "radius_px", "step_direction",
    "FETCH_MODES", "BORDER_MODES", "AZIMUTHS", "NOISES", "SLICE_SAMPLINGS", "Footprint", "GradientRows", "PerspectiveBilinearDepth",
    "SampleAlong",
]

"""Feature tracks: pairwise matches chained across views (connected components of the match graph)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from torchsfm.numerics import component_labels

PAIR_SUM_CHUNK = 4096  # tracks per dense (views × tracks) table of Tracks.pair_sums


@dataclass
class Tracks:
    """Corners grouped into tracks.

    Fields:
        view: (T,) int64 view of each track observation; corner: (T,) its corner index in that view;
        track: (T,) its track id in [0, num_tracks). Sorted by track.
        num_tracks: number of tracks (each has observations in at least two distinct views).

    A value: its fields are not changed once made (the indices by view and by track are computed
    on first use and kept; observations found later make a new ``Tracks``).
    """

    view: Tensor
    corner: Tensor
    track: Tensor
    num_tracks: int

    def of_view(self, view: int) -> Tensor:
        """The observation indices (into ``view``, ``corner``, ``track``) of one view, ascending:
        (K_v,), from one sort of the observations by view, made on the first call."""
        order, starts, counts = self._by_view
        if view >= counts.numel():
            return order[:0]
        start = int(starts[view])
        return order[start:start + int(counts[view])]

    def observations_of(self, tracks: Tensor) -> tuple[Tensor, Tensor]:
        """Every observation of the (M,) ``tracks``, track by track in their order (ascending
        within each), and the position in ``tracks`` of the track each belongs to: two (K,)."""
        starts, counts = self._by_track
        lengths = counts[tracks]
        owner = torch.repeat_interleave(torch.arange(tracks.numel()), lengths)
        within = torch.arange(owner.numel()) - (torch.cumsum(lengths, 0) - lengths)[owner]
        return starts[tracks][owner] + within, owner

    @cached_property
    def _by_view(self) -> tuple[Tensor, Tensor, Tensor]:
        """The observations sorted by view (stably), and each view's first place and count there."""
        counts = torch.bincount(self.view)
        return torch.argsort(self.view, stable=True), torch.cumsum(counts, 0) - counts, counts

    @cached_property
    def _by_track(self) -> tuple[Tensor, Tensor]:
        """Each track's first observation and its number of observations (sorted by track)."""
        counts = self.lengths()
        return torch.cumsum(counts, 0) - counts, counts

    def lookup(self, view: int, num_corners: int) -> Tensor:
        """Track id of each corner of a view, -1 where it has none: (num_corners,)."""
        table = torch.full((num_corners,), -1, dtype=torch.long)
        mine = self.of_view(view)
        table[self.corner[mine]] = self.track[mine]
        return table

    def pair_sums(self, num_views: int, left: Tensor, right: Tensor) -> Tensor:
        """(V, V) float64: for views i, j, the sum over the tracks seen in both of ``left`` at the
        track's observation in i times ``right`` at its observation in j (``left``, ``right``
        (T,) per observation). Dense (V × tracks) tables, a chunk of tracks at a time."""
        total = torch.zeros(num_views, num_views, dtype=torch.float64)
        bounds = torch.searchsorted(self.track, torch.arange(0, self.num_tracks + PAIR_SUM_CHUNK, PAIR_SUM_CHUNK)).tolist()
        for chunk, (start, end) in enumerate(zip(bounds[:-1], bounds[1:])):
            if start == end:
                continue
            where = (self.view[start:end], self.track[start:end] - chunk * PAIR_SUM_CHUNK)
            a = torch.zeros(num_views, PAIR_SUM_CHUNK, dtype=torch.float64).index_put_(where, left[start:end].double())
            b = torch.zeros(num_views, PAIR_SUM_CHUNK, dtype=torch.float64).index_put_(where, right[start:end].double())
            total += a @ b.T
        return total

    def covisibility(self, num_views: int) -> Tensor:
        """(V, V) int64: the number of tracks seen in both views (0 on the diagonal)."""
        ones = torch.ones(self.view.numel(), dtype=torch.float64)
        return self.pair_sums(num_views, ones, ones).round().long().fill_diagonal_(0)

    def shared(self, view1: int, view2: int) -> tuple[Tensor, Tensor]:
        """Corner indices (M,), (M,) in view1 and view2 of the M tracks seen in both."""
        in1, in2 = self.of_view(view1), self.of_view(view2)
        both = torch.isin(self.track[in1], self.track[in2])
        tracks = self.track[in1][both]
        corner2 = torch.full((self.num_tracks,), -1, dtype=torch.long)
        corner2[self.track[in2]] = self.corner[in2]
        return self.corner[in1][both], corner2[tracks]

    def lengths(self) -> Tensor:
        """(num_tracks,) number of views of every track."""
        return torch.bincount(self.track, minlength=self.num_tracks)

    def gather(self, per_view: list[Tensor]) -> Tensor:
        """Each observation's row of a per-view, per-corner table (e.g. corner pixels (K_v, 2)):
        (T, ...), one gather."""
        offsets = torch.cumsum(torch.tensor([0] + [values.shape[0] for values in per_view]), 0)
        return torch.cat(per_view)[offsets[self.view] + self.corner]

    def dense(self, corners: list[Tensor], num_views: int) -> tuple[Tensor, Tensor]:
        """Every track's pixels in every view, (V, T, 2) float64 (0 where unseen), and (V, T) bool
        where it is seen, from the per-view corners (K_v, 2)."""
        pixels = torch.zeros(num_views, self.num_tracks, 2, dtype=torch.float64)
        visible = torch.zeros(num_views, self.num_tracks, dtype=torch.bool)
        pixels[self.view, self.track] = self.gather(corners).double()
        visible[self.view, self.track] = True
        return pixels, visible

    def subset(self, keep: Tensor) -> Tracks:
        """The tracks where ``keep`` (num_tracks,) bool is True, renumbered in order."""
        mine = keep[self.track]
        _, track = torch.unique(self.track[mine], return_inverse=True)
        return Tracks(view=self.view[mine], corner=self.corner[mine], track=track, num_tracks=int(keep.sum()))


def build_tracks(num_corners: list[int], matches: dict[tuple[int, int], tuple[Tensor, Tensor]]) -> Tracks:
    """Chain pairwise matches into tracks.

    Args:
        num_corners: corners per view.
        matches: for view pairs (i, j), matched corner indices (index_i, index_j) of equal length.

    Returns:
        :class:`Tracks`. Components that contain two corners of the same view are inconsistent
        (a corner cannot match two corners of one image) and are dropped whole.
    """
    offsets = torch.cumsum(torch.tensor([0] + num_corners), 0)
    total = int(offsets[-1])
    views_of = torch.repeat_interleave(torch.arange(len(num_corners)), torch.tensor(num_corners, dtype=torch.long))
    edges = [torch.stack([offsets[i] + a, offsets[j] + b]) for (i, j), (a, b) in matches.items() if a.numel()]
    labels = component_labels(*torch.cat(edges, dim=1), total) if edges else torch.arange(total)
    component_size = torch.bincount(labels, minlength=total)
    in_component = component_size[labels] >= 2
    # a consistent component has exactly one corner per view it touches (no (corners × views) table: long videos)
    _, inverse, repeats = torch.unique(labels[in_component] * len(num_corners) + views_of[in_component],
                                       return_inverse=True, return_counts=True)
    consistent = torch.ones(total, dtype=torch.bool)
    consistent[labels[in_component][repeats[inverse] > 1]] = False
    keep = in_component & consistent[labels]
    components, track = torch.unique(labels[keep], return_inverse=True)
    order = torch.argsort(track, stable=True)
    global_ids = torch.nonzero(keep).flatten()[order]
    view = views_of[global_ids]
    return Tracks(view=view, corner=global_ids - offsets[view], track=track[order], num_tracks=components.numel())


def chained_matches(num_corners: list[int], matches: dict[tuple[int, int], tuple[Tensor, Tensor]], min_views: int
                    ) -> dict[tuple[int, int], tuple[Tensor, Tensor]]:
    """Of pairwise ``matches`` (as :func:`build_tracks` takes them), those that chain among
    themselves into tracks seen in at least ``min_views`` views, per pair (pairs left empty are
    left out). A pair's chance agreements rarely continue into a third view; a moving body's
    matches do."""
    tracks = build_tracks(num_corners, matches)
    offsets = torch.cumsum(torch.tensor([0] + num_corners), 0)
    chained = torch.zeros(int(offsets[-1]), dtype=torch.bool)
    chained[offsets[tracks.view] + tracks.corner] = (torch.bincount(tracks.track, minlength=tracks.num_tracks) >= min_views)[tracks.track]
    kept = {}
    for (i, j), (a, b) in matches.items():
        both = chained[offsets[i] + a] & chained[offsets[j] + b]
        if bool(both.any()):
            kept[(i, j)] = (a[both], b[both])
    return kept

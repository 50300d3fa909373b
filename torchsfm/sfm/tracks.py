"""Feature tracks: pairwise matches chained across views (connected components of the match graph)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Tracks:
    """Corners grouped into tracks.

    Fields:
        view: (T,) int64 view of each track observation; corner: (T,) its corner index in that view;
        track: (T,) its track id in [0, num_tracks). Sorted by track.
        num_tracks: number of tracks (each has observations in at least two distinct views).
    """

    view: Tensor
    corner: Tensor
    track: Tensor
    num_tracks: int

    def lookup(self, view: int, num_corners: int) -> Tensor:
        """Track id of each corner of a view, -1 where it has none: (num_corners,)."""
        table = torch.full((num_corners,), -1, dtype=torch.long)
        mine = self.view == view
        table[self.corner[mine]] = self.track[mine]
        return table

    def lengths(self) -> Tensor:
        """(num_tracks,) number of views of every track."""
        return torch.bincount(self.track, minlength=self.num_tracks)

    def gather(self, per_view: list[Tensor]) -> Tensor:
        """Each observation's row of a per-view, per-corner table (e.g. corner pixels (K_v, 2)):
        (T, ...), one gather."""
        offsets = torch.cumsum(torch.tensor([0] + [values.shape[0] for values in per_view]), 0)
        return torch.cat(per_view)[offsets[self.view] + self.corner]

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
    labels = torch.arange(total)
    if edges:
        u, v = torch.cat(edges, dim=1)
        while True:  # label propagation with pointer jumping: every component ends at its smallest id
            smallest = torch.minimum(labels[u], labels[v])
            updated = labels.scatter_reduce(0, u, smallest, "amin").scatter_reduce(0, v, smallest, "amin")
            updated = updated[updated]
            if torch.equal(updated, labels):
                break
            labels = updated
    component_size = torch.bincount(labels, minlength=total)
    in_component = component_size[labels] >= 2
    # a consistent component has exactly one corner per view it touches
    per_view = torch.zeros(total, len(num_corners), dtype=torch.long).index_put_((labels, views_of), torch.ones(total, dtype=torch.long), accumulate=True)
    consistent = (per_view <= 1).all(-1)[labels]
    keep = in_component & consistent
    components, track = torch.unique(labels[keep], return_inverse=True)
    order = torch.argsort(track, stable=True)
    global_ids = torch.nonzero(keep).flatten()[order]
    view = views_of[global_ids]
    return Tracks(view=view, corner=global_ids - offsets[view], track=track[order], num_tracks=components.numel())

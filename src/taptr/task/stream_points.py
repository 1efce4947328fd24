"""A stream's points: the user's, with their identifiers, and the support around them.

A model tracks one list of points in the order they joined: user points and support
points interleaved as a stream adds and removes them. The support is drawn when the first
frame (or window) is decoded, from the user points known then (`draw_support`); points
added later bring what their scheme's ``added`` says (`support_added`: with
``local_and_grid``, their own local points), and removing a user point removes the
support around it (`remove`). Grid and context points belong to no user point and stay.

`taptr.api.online.OnlineTracker` and `taptr.onnx.online.OnnxOnlineTracker` both keep
their points here, and add to or keep from their model's list what this says.

Shapes: N user points, N_t points the model tracks, K support points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from taptr.task.support_schemes import SupportPattern, SupportPoints, SupportScheme, no_points


@dataclass
class StreamPoints:
    """Who is who among a stream's points.

    Attributes:
        queries: (N, 3) float32 (t, x, y) pixels of the user's points, in order.
        point_ids: identifier of each user point, in order.
        next_id: identifier of the next user point.
        is_support: (N_t,) bool over the model's points: True for support points.
        support_of: (N_t,) int64 over the model's points: the identifier of the user point
            a support point surrounds (it leaves with it), else −1.
        scheme: the stream's support scheme, once drawn.
    """

    queries: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_ids: list[int] = field(default_factory=list)
    next_id: int = 0
    is_support: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    support_of: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    scheme: SupportScheme | None = None

    @property
    def users(self) -> np.ndarray:
        """(N_t,) bool: the model's points that are the user's."""
        return ~self.is_support

    def add_queries(self, queries: np.ndarray) -> list[int]:
        """Appends user points ((M, 3) checked pixel queries); returns their identifiers."""
        ids = list(range(self.next_id, self.next_id + len(queries)))
        self.next_id += len(queries)
        self.point_ids += ids
        self.queries = np.concatenate((self.queries, queries.astype(np.float32)))
        self._append(np.zeros(len(ids), bool), np.full(len(ids), -1, np.int64))
        return ids

    def draw_support(
        self,
        scheme: SupportScheme,
        pattern: SupportPattern,
        xy: np.ndarray,
        *,
        caller_draws: bool = False,
    ) -> SupportPoints:
        """Sets the stream's scheme and returns its support of the user points known now.

        Args:
            scheme: the scheme chosen for them.
            pattern: its numbers, in the unit and type of ``xy``.
            xy: (N, 2) the user points' positions in the model's units.
            caller_draws: the caller draws a ``drawn`` scheme's points itself
                (`taptr.api.context_points`); without it, such a scheme's ``points`` says why it
                cannot be drawn here.

        Returns:
            The support points, parents as identifiers.
        """
        self.scheme = scheme
        if scheme.drawn and caller_draws:
            return no_points(xy)
        support = scheme.points(self.queries[:, 0].astype(np.int64), xy, pattern)
        return self._with_ids(support, np.array(self.point_ids, np.int64))

    def support_added(
        self, ids: list[int], starts: np.ndarray, xy: np.ndarray, pattern: SupportPattern
    ) -> SupportPoints:
        """The support points ``ids`` (just added) bring, parents as identifiers.

        None before the support is drawn: the points are among those it is drawn from.
        """
        if self.scheme is None:
            return no_points(xy)
        support = self.scheme.added(starts, xy, pattern)
        return self._with_ids(support, np.array(ids, np.int64))

    def add_support(self, parents: np.ndarray) -> None:
        """Records support points appended to the model's list; ``parents`` (K,) their ids."""
        self._append(np.ones(len(parents), bool), np.asarray(parents, np.int64))

    def remove(self, ids: list[int]) -> np.ndarray:
        """Forgets user points and the support around them.

        Returns:
            (N_t,) bool over the model's points: the ones to keep.

        Raises:
            ValueError: unknown identifiers.
        """
        removed = set(ids)  # once: a set per point made removing half of 100,000 quadratic
        unknown = sorted(removed.difference(self.point_ids))
        if unknown:
            more = f", ... ({len(unknown):,} in all)" if len(unknown) > 10 else ""
            raise ValueError(f"unknown point ids: {unknown[:10]}{more}")
        keep_users = np.array([pid not in removed for pid in self.point_ids], bool)
        gone = np.array(sorted(removed), np.int64)
        keep = self.is_support & ~np.isin(self.support_of, gone)
        keep[~self.is_support] = keep_users
        self.is_support = self.is_support[keep]
        self.support_of = self.support_of[keep]
        self.queries = self.queries[keep_users]
        self.point_ids = [pid for pid in self.point_ids if pid not in removed]
        return keep

    def _append(self, support: np.ndarray, parents: np.ndarray) -> None:
        self.is_support = np.concatenate((self.is_support, support))
        self.support_of = np.concatenate((self.support_of, parents))

    @staticmethod
    def _with_ids(support: SupportPoints, ids: np.ndarray) -> SupportPoints:
        """Parents as identifiers: index i among the queries given → ids[i]; −1 stays."""
        lookup = np.append(ids, -1).astype(np.int64)  # index −1 reads the −1 appended
        return support._replace(parents=lookup[support.parents])

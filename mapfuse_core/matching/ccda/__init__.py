"""Map-to-map matching by Combined Constraint Data Association (``docs/method.md`` §5.1).

CCDA (Bailey, Nebot, Rosenblatt, Durrant-Whyte, ICRA 2000) finds which features of
map ``A`` are the same physical features as features of map ``B`` when the rigid
motion between the two frames is unknown.  In mapfuse ``A`` is the SLAM global map
(frame ``Wglobal``) and ``B`` the a-priori known map (frame ``Wknown``); the result
is ``x^Wglobal_Wknown`` (the paper's eq. 12) with its covariance.

The method, step by step:

1. **Nodes (unary test).**  A node of the correspondence graph is a pair
   ``(i in A, j in B)`` of the same kind.  Circles must also have compatible radii:
   ``(r_a − r_b)² ≤ χ²₁(p) · (σ²_ra + σ²_rb)``.  Lines have no frame-free unary
   property (their offset and angle change with the frame), so every line pair is
   a node.
2. **Edges (binary test).**  Two nodes ``(i, j)`` and ``(k, l)`` with ``i ≠ k`` and
   ``j ≠ l`` are joined when the rigid-motion invariants of the pair ``(i, k)`` in
   ``A`` agree with those of ``(j, l)`` in ``B`` within a χ² gate computed from
   the first-order propagated covariances of the four features:

   * circle–circle: distance between the centres (1 dof);
   * circle–line: unsigned distance from the centre to the line (1 dof);
   * line–line: signed angle from the first line to the second, modulo π (1 dof);
     when both pairs are parallel (``|angle| ≤ parallel_tol_rad`` in both maps) also
     the unsigned lateral distance of the second line's origin from the first line,
     tested jointly with the angle (2 dof, with their correlation).

   Where both maps give line extents, line–line edges also need the segments to
   agree along the lines: from the intersection of non-parallel lines, and for
   parallel ones through the single offset along them that one motion gives both
   pairings (``graph._corners_overlap``, ``graph._parallel_overlap``).

   Lines enter only through their lateral offset and angle: every line covariance
   is first reduced to the 2×2 covariance of ``(e_lat, e_θ)``, the SPmap
   perturbation ``L ⊕ (0, e_lat, e_θ)``, so the along-line pseudo-variance is never
   used.  The invariants are computed with numpy for all feature pairs of each map;
   the pairs of ``A`` are joined to those of ``B`` by sorting ``B``'s values and
   searching a window around each value of ``A`` (so the cost grows with the number
   of edges, not with ``|A|²·|B|²``), and each candidate is then tested exactly.
3. **A clique that can be accepted.**  Nodes that cannot be in a clique of
   ``min_pairings − 1`` nodes (one of slack for the re-association) are pruned
   (k-core), then a clique of that size is searched by
   :class:`~mapfuse_core.matching.ccda.clique._CliqueGraph`: the greedy clique when it
   is large enough, else the first the exact branch and bound finds (networkx's
   ``max_weight_clique`` takes seconds on the graphs of maps of a few hundred
   features; see that class for the method).  Proving which clique is the largest
   decides nothing and is what exhausts a budget on dense graphs.
4. **Transform and verification.**  The transform is estimated from the clique's
   pairings by weighted least squares (:func:`estimate_transform`).  Every pairing
   is then tested *leave-one-out*: its residual against the transform fitted to
   the other pairings, with that fit's covariance added (a wrong line pairing can
   bend a fit of eight pairings by a metre and then pass its own in-sample gate).
   The worst failure is dropped and the fit repeated until all pass.  Finally
   every node is re-associated with the fitted transform (one-to-one, nearest
   first, gate widened by the transform's covariance) and refitted: the clique
   may have picked the wrong one of two collinear walls, or missed a pairing
   whose edge to one member failed its gate by chance.
5. **Acceptance.**  The match is accepted only with at least ``min_pairings``
   pairings (the paper: "more than three"), a covariance showing that the
   pairings fix the transform, and fix it without any one of them (a pairing
   that alone fixes a direction cannot be checked by the others), and no
   competing hypothesis: the nodes that agree
   with the transform are removed, the next clique large enough to compete is
   searched and fitted, and so on while one remains; if a
   hypothesis whose transform is incompatible with the best one has comparable
   support (at least ``max(min_pairings, ⌈rival_fraction · best⌉)`` pairings), the
   map is symmetric or repetitive at the scale of the noise and the match is
   rejected as ``"ambiguous"`` rather than chosen by a count.  A search that runs
   out of its budget (``max_clique_work``, ``max_hypotheses``) before every rival
   is ruled out returns ``"search_limit"``: refusing is always allowed, accepting
   an unverified match never.

Both maps are first translated to the centroids of their feature positions, and
the transform is translated back at the end (:func:`~mapfuse_core.matching.ccda.prepare._centred`):
invariants, gates and fits then see coordinates of the size of the maps, so the
result does not depend on where either map's origin is (a surveyed map in
UTM-like coordinates, 10⁶–10⁷ m, matches as it does at the origin).

Choices the paper leaves open (all configurable in :class:`CCDAParams`):

* *(choice)* One gate probability, ``gate_prob = 0.999``, for the unary, binary
  and pairing tests.  A true pair of features fails one test with probability
  ``1 − p``; a clique of ``n`` true pairings needs ``n(n−1)/2`` edges, so a strict
  gate is needed for large overlaps to stay a single clique (and step 4 recovers
  the few true pairings the clique still misses).
* *(choice)* Correlations between features of one map are ignored (a
  :class:`KnownMapArrays` only holds marginal covariances).  In a SLAM map nearby
  features are positively correlated, so their relative geometry is better known
  than the marginals say: ignoring the correlation makes the gates looser, which
  can add spurious edges but does not cut true ones.
* *(choice)* Distances are unsigned (circle–line and parallel line–line) because a
  line has no direction; the line–line angle keeps its sign (a rotation preserves
  it, a reflection would not).  Circle–circle distances cannot tell a map from
  its mirror image: mirror cliques of symmetric maps are found and then fail the
  transform fit of step 4.
* *(choice)* Two lines are parallel for the distance test when the angle between
  them is at most ``parallel_tol_rad`` in both maps.  For lines that are only
  nearly parallel the distance depends on where along the lines it is measured,
  and SPmap origins sit at segment midpoints that differ between maps; the
  variance of the distance is therefore increased by
  ``(sin(max |angle|) · parallel_along_std_m)²``.
* *(choice)* A line's covariance is read in its own frame: lateral variance
  ``nᵀ Σ_xy n`` with ``n`` the normal of the line's *own* angle, as extraction
  (pseudo-variance along the fitted direction) and the EKF (along-line component
  projected out) state it.  A pseudo-variance ``L²`` along some other direction
  would leak ``L² sin²δ`` into the lateral one.
* *(choice)* Every variance gets a small floor (``var_floor_m``,
  ``var_floor_rad``) so that noise-free maps (e.g. the true world, whose
  covariances are zero) still give invertible gates.  Noisy maps whose covariances
  are stated as zero or near zero then get gates at the floor: true pairs fail
  them, the graph stays small, and the call refuses (``"too few pairings"``, or
  ``"search_limit"`` within the budget) instead of exploding.
* *(choice)* The transform is "fixed" when the largest standard deviation of the
  position (worst direction) of the centroid of the paired ``B`` features, mapped
  into ``A``, is at most ``max_transform_std_xy_m`` and that of its angle at most
  ``max_transform_std_theta_rad``.  The centroid of the pairings is where the
  match is judged: the uncertainty at a map's origin adds the lever arm of the
  angle out to wherever that origin happens to be.  Degenerate sets (only
  parallel lines, a single circle with lines through it, …) have a rank-deficient
  information matrix; its null directions get a variance of ``1 / 1e-12``.
* *(choice)* Evidence that repetition cannot fool: a competing hypothesis counts
  when its transform differs from the best one beyond the χ²₃ gate of their summed
  covariances and it has at least ``max(min_pairings, ⌈rival_fraction · best⌉)``
  pairings after re-association (step 4), ``rival_fraction = 0.5``.  In a periodic
  world (city blocks, a grid of identical trees) a shift by one period keeps
  ``(k − 1)/k`` of the pairings of a local map spanning ``k`` periods inside the
  known map, and all of them when the local map reaches past the known map's
  edge (then the wrong shift has *more* support than the truth); either way the
  rival has at least half the support and the match is refused.  A rule "best
  beats the runner-up by a fixed margin" accepts those shifts; it remains
  available (``ambiguity_margin`` set to an integer) for maps known not to repeat.
  Chance cliques of unrelated features stay near ``min_pairings`` whatever the
  overlap, so large true matches are not refused for them.  Rivals are searched
  down to cliques one node smaller than the rival floor, because removing the
  best hypothesis' nodes also removes a feature both share (the centre of a
  rotational symmetry) from the rival's clique; the search stops as soon as the
  match is proven ambiguous.  What no rule can detect: a local map that lies
  mostly outside the known map, where a wrong placement explains more than half
  of it and the truth less (``docs/results/ccda.md``).
* *(choice)* The exact clique search spends a deterministic budget,
  ``max_clique_work`` work units (one per branch-and-bound node plus one per
  candidate vertex it colours or prunes) over all searches of one call, so the
  outcome is the same on every machine; exhausting it gives ``"search_limit"``.
  Dense angle-only edges (perpendicular walls of a city grid, covariances stated
  as zero) make the exact search exponential without it.
* *(choice)* The returned pairings are those of step 4: consistent with the
  estimated transform leave-one-out, one-to-one, each feature with its nearest
  compatible partner.  ``clique_size`` reports the maximum clique's inliers.
* *(choice)* Graphs beyond ``max_edges`` edges are not searched (the exact search
  costs about ``edges × nodes / 64`` word operations); the call returns
  ``"graph too large"`` after bounded time and memory.

Everything fails cleanly: empty or too small maps and every rejection give a
:class:`CCDAResult` with ``accepted=False`` and a reason; only malformed input
(non-finite numbers, wrong shapes, unknown kinds, bad parameters) raises
:class:`ValueError`.
"""

from mapfuse_core.matching.ccda.clique import _CliqueGraph as _CliqueGraph
from mapfuse_core.matching.ccda.match import ccda_match
from mapfuse_core.matching.ccda.params import REASONS, CCDAParams, CCDAResult
from mapfuse_core.matching.ccda.prepare import _prepare as _prepare
from mapfuse_core.matching.ccda.residuals import _pair_set as _pair_set
from mapfuse_core.matching.ccda.residuals import _residuals as _residuals
from mapfuse_core.matching.ccda.residuals import pairing_chi2
from mapfuse_core.matching.ccda.transform import _cost as _cost
from mapfuse_core.matching.ccda.transform import _estimate as _estimate
from mapfuse_core.matching.ccda.transform import _gauss_newton as _gauss_newton
from mapfuse_core.matching.ccda.transform import _normal_equations as _normal_equations
from mapfuse_core.matching.ccda.transform import _solve as _solve
from mapfuse_core.matching.ccda.transform import _step as _step
from mapfuse_core.matching.ccda.transform import estimate_transform

__all__ = [
    "REASONS",
    "CCDAParams",
    "CCDAResult",
    "ccda_match",
    "estimate_transform",
    "pairing_chi2",
]

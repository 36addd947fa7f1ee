"""The localizer's settings: the YAML of ``rangemcl localize --config``, one dataclass per part of the
filter, checked by :meth:`LocalizerSettings.check`. The defaults live here and only here: the filter's
parts are made from these classes by :mod:`rangemcl.localization.factory`, and their constructors take
every setting as a required argument (``tests/rangemcl/localization/test_settings.py`` checks both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rangemcl.errors import InputError
from rangemcl.localization.scan_prep import RAY_SAMPLINGS

# ---------------------------------------------------------------------------------------------- settings


@dataclass
class ParticleSettings:
    """How many particles the filter holds in each phase (global search, converged, tracking), when it
    resamples, how it roughens the copies, and how the pose estimate is formed from them."""

    global_count: int = 10000
    """Particles spread over the drivable area for global localization and again after each recovery.
    While searching, the KLD bound shrinks the cloud but never grows it beyond this count."""
    converged_count: int = 100
    """Particles kept once a search declares convergence (resampled from the winning hypothesis, or from
    the whole cloud with `convergence.method: tiles`); the converged filter goes on with this many."""
    tracking_count: int = 100
    """Particles drawn around the given start pose in tracking mode (`--mode tracking`)."""
    tracking_sigma_xy_m: float = 0.5
    """Standard deviation in m, in x and y, of the tracking-mode start around the given pose (normal);
    0 puts every particle on it."""
    tracking_sigma_yaw_deg: float = 3.0
    """Standard deviation in degrees of the tracking-mode start's yaw around the given pose."""
    resample_neff_ratio: float = 0.75
    """Resampling threshold, a share in (0, 1]: a converged filter (and a search with `convergence.method:
    tiles`) resamples when the effective sample size N_eff falls below this share of the particle count.
    The hypothesis search resamples at every update regardless."""
    jitter_xy_m: float = 0.05
    """Roughening in m once converged: a normal offset of this standard deviation in x and y is added to
    every copy after each resampling, which keeps the copies of one particle apart. 0: none."""
    jitter_yaw_deg: float = 0.5
    """Roughening in degrees of yaw after each resampling once converged (as `jitter_xy_m`); 0: none."""
    global_jitter_xy_m: float = 0.05
    """Roughening in m of x and y after each resampling before convergence, which lets a cluster explore
    around its particles. Kept small: the range likelihood is sharply peaked, a copy roughened far falls
    off the peak, and the search's polish (`convergence.polish_hypotheses`) explores instead."""
    global_jitter_yaw_deg: float = 0.25
    """Roughening in degrees of yaw after each resampling before convergence (as `global_jitter_xy_m`)."""
    estimate_best_share: float = 0.8
    """Share in (0, 1] of the particles, heaviest first, whose weighted mean (circular in yaw) is the pose
    estimate; 1: the whole cloud's weighted mean. While the hypothesis search runs, the estimate is the
    leading hypothesis's centroid instead."""


@dataclass
class MotionSettings:
    """The odometry motion model: when the filter weighs a scan, how much noise each prediction adds, and
    the online calibration of the odometry's translation scale and the gyro's yaw-rate bias."""

    update_distance_m: float = 0.2
    """Distance in m the car must drive since the last update before the particles are moved and weighed
    with a scan (or turn `update_angle_deg`, whichever comes first); between updates the estimate follows
    the odometry. 0: every frame."""
    update_angle_deg: float = 5.0
    """Turn in degrees since the last update that also triggers an update (see `update_distance_m`)."""
    rot_per_rot: float = 0.05
    """Motion model noise alpha1 (Thrun et al.'s odometry model), a factor: standard deviation of each
    rotation of the increment, in rad per rad turned."""
    rot_per_trans: float = 0.005
    """Motion model noise alpha2, in rad per m driven: rotation noise that grows with the distance."""
    trans_per_trans: float = 0.05
    """Motion model noise alpha3, a factor (m per m driven): translation noise that grows with the
    distance."""
    trans_per_rot: float = 0.05
    """Motion model noise alpha4, in m per rad turned: translation noise that grows with the turns."""
    odometry_scale: float = 1.0
    """The odometry's translation scale as known, a factor (> 0) every odometry translation is multiplied
    by before the prediction; the online scale calibration starts from it."""
    gyro_bias_deg_s: float = 0.0
    """The gyro's yaw-rate bias as known, in degrees per second: times each frame's duration, it is
    subtracted from the odometry's turn; the online bias calibration starts from it. 0: none."""
    calibrate_scale: bool = True
    """Estimate the odometry's translation scale online while converged, by the method `calibration`
    names; false: keep `odometry_scale`."""
    calibrate_gyro_bias: bool = True
    """Estimate the gyro's yaw-rate bias online while converged; false: keep `gyro_bias_deg_s`."""
    calibration_window_m: float = 100.0
    """Memory of the scale estimate in m driven (`calibration: estimator`): past evidence loses weight by
    a factor 1/e per this distance."""
    calibration_window_s: float = 300.0
    """Memory of the bias estimate in seconds (`calibration: estimator`): past evidence loses weight by a
    factor 1/e per this time."""
    calibration_prior_m: float = 3.0
    """Weight of the configured `odometry_scale` in the estimator, as m of evidence (forgotten like the
    rest); larger: the estimate leaves the configured value more slowly."""
    calibration_prior_s: float = 0.3
    """Weight of the configured `gyro_bias_deg_s` in the estimator, as seconds of evidence."""
    calibration_settle_updates: int = 10
    """Updates after each convergence (or tracking start) left out of the calibration, while the cloud
    settles on its place."""
    calibration_outlier_m: float = 0.25
    """An interval between two converged updates whose estimated translation disagrees with the
    calibrated odometry by more than this, in m, is left out of the estimator (a recovery, a
    refinement's jump)."""
    calibration_outlier_deg: float = 2.0
    """As `calibration_outlier_m`, for the interval's turn, in degrees."""
    calibration_min_scale: float = 0.8
    """Lower bound of the scale estimate, a factor (both calibration methods keep it within the bounds)."""
    calibration_max_scale: float = 1.25
    """Upper bound of the scale estimate, a factor; at least `calibration_min_scale`."""
    calibration: str = "estimator"
    """How scale and bias are estimated: `estimator` (a slow estimator on the filter's own corrections
    between converged updates) or `particles` (scale and bias as extra state of each converged particle,
    selected by the weighting: `rangemcl.localization.calibration.ParticleCalibration`)."""
    calibration_sigma_scale: float = 0.03
    """`calibration: particles`: standard deviation (a factor) of each particle's scale, drawn around the
    running estimate at each convergence."""
    calibration_sigma_bias_deg_s: float = 0.5
    """`calibration: particles`: standard deviation in degrees per second of each particle's gyro bias,
    drawn around the running estimate at each convergence."""
    calibration_walk_scale: float = 0.001
    """`calibration: particles`: random walk of a particle's scale per square root of a metre driven, so
    that resampling does not collapse the states."""
    calibration_walk_bias_deg_s: float = 0.005
    """`calibration: particles`: random walk of a particle's gyro bias, in degrees per second per square
    root of a second."""


@dataclass
class ObservationSettings:
    """The observation model and the scan's rays that weigh the particles: which model, which measured
    points are cast from each particle, and how their residuals count."""

    model: str = "range"
    """The observation model that scores the particles: `range` (the paper's Eq. 5 on the mean range
    residual), or the baselines `overlap`, `likelihood_field` and `histogram`
    (`rangemcl.localization.models`)."""
    sigma_m: float = 0.25
    """σ_d of Eq. 5 in m (`model: range`): the log-likelihood of a mean residual d is −½ d² / σ_d², so a
    smaller σ_d makes each update tell places apart more sharply. The paper uses 5.0 m, its reference code
    2.0 m."""
    rays: int = 500
    """Measured points cast from every particle per update, in rays: a random subset of the scan's valid
    points drawn as `ray_sampling` says (all of them when the scan has fewer). The cost grows with it."""
    ray_sampling: str = "structure"
    """How the rays are drawn: `points` (each valid point alike), `elevation` (each 2-degree elevation
    band alike, so that a sensor whose beams crowd the road near the car still sends rays farther and
    higher) or `structure` (at most `ground_share` of the rays from the road, i.e. points within 0.5 m of
    the sensor's ground, the rest from what stands on it, each part evenly over the elevation bands)."""
    ground_share: float = 0.2
    """`ray_sampling: structure`: the road's share of the rays, in [0, 1]: the road fits almost anywhere,
    so its rays say little about the place."""
    tall_share: float = 0.6
    """`ray_sampling: structure`: of the rays not on the road, the share in [0, 1] drawn from points at
    least `tall_m` above the ground (facades above the parked cars, which change between drives).
    0: all structure alike."""
    tall_m: float = 2.0
    """`ray_sampling: structure`: height in m above the sensor's ground from which a point counts as tall
    (`tall_share`)."""
    margin_m: float = 2.0
    """Margin in m past the measured range up to which each ray is cast; a ray that meets nothing by then
    counts as a residual of this margin."""
    cap_m: float | None = 1.0
    """Per-ray residual cap in m (the robust variant of Eq. 5, against moving and changed objects); rays
    more than this off the map's surface either way also leave the inlier share (of those short of it, at
    most half). `None`: no cap, the paper's plain mean."""
    cap_beyond_m: float | None = 0.5
    """Cost in m of a ray measured more than `cap_m` longer than the map's surface: it passed where the
    map holds an object that is gone, weak evidence against the pose. At most `cap_m`; `None`: `cap_m`
    (both directions alike)."""
    cap_short_m: float | None = None
    """Cost in m of a ray measured more than `cap_m` shorter than the map's surface (or meeting nothing
    of the map): at the car's true pose it met an object the map lacks (a car parked since the mapping
    drive, a moving actor), which every pose explains alike, weak evidence against the pose. At most
    `cap_m`; `None`: `cap_m` (both directions alike)."""
    movable_height_m: float | None = 4.0
    """Height in m above the ground up to which the world may have changed since the mapping drive (the
    tallest vehicle: parked cars come and go, vehicles and people move). `cap_short_m` and `cap_beyond_m`
    apply only to rays whose measured point (short) or whose map surface (beyond) lies below it; above it
    nothing appears or vanishes between drives, and such a ray costs `cap_m`. `None`: every height (the
    method of version 0.17 and before)."""
    vehicle_length_m: float | None = 7.0
    """Leave out the scan's points on objects that may be parked vehicles: objects standing on the road
    (points in touching 0.3 m cells) from 1 m up to this long, in m (the longest parked vehicle), at
    most 3 m wide and no taller than `movable_height_m`. Parked cars stand a few decimetres off where the
    mapping drive's stood, or not at all, and pull the pose by that much where little else fixes it.
    Poles and trunks (under 1 m) stay. `None`: every point (the method of version 0.17 and before)."""
    explain_beyond: bool = True
    """A ray measured more than `cap_m` beyond the map's surface costs `cap_beyond_m` only where the map
    has a surface within `cap_m` of its measured point: the scan saw past an object gone since the mapping
    drive to what the map holds behind it. Otherwise it passed through the map into nothing the map
    knows, which a removed object does not explain, and costs `cap_m`. One more ray cast per such ray.
    `false`: every such ray costs `cap_beyond_m` (the method of version 0.17 and before)."""
    rendering: str = "exact"
    """How the filter renders many poses that lie close around a few: `exact` (every pose's rays cast
    through the map) or `planar` (the rays cast once from a reference pose; each pose's rendered range is
    where its own ray meets the plane of the surface the reference's ray met). `planar` renders a converged
    cloud about its estimate, and each local grid (the search's polish around its hypotheses, the
    challenge's, the second opinion's look around a better place and its look at the past) about
    references within 1 m and 3 degrees of its poses (27 for a grid of +-2 m and +-8 degrees). Within a
    metre and a few degrees almost every ray meets the same surface, so `planar` ranks the poses nearly as
    `exact` does for a fraction of the rays; a converged cloud spread wider than 1 m or 3 degrees from its
    estimate is rendered exactly, and so is the search's cloud of particles spread over the map."""
    min_range_m: float = 2.0
    """Returns closer than this, in m, are ignored (the car itself)."""
    max_range_m: float = 40.0
    """Returns farther than this, in m, are ignored: keep it at the map builder's `scans.max_range_m`, the
    range the map was meshed to. Also the histogram model's range and part of the radius around the
    particles that a map within a memory budget keeps loaded."""
    deskew: bool = True
    """De-skew the rays where the scan has per-point firing times: each point is moved by the part of the
    frame's odometry after its firing time (the motion taken as uniform over the frame)."""
    level_with_imu: bool = True
    """Rotate the scan by the IMU's roll and pitch, where the sequence has them, before casting and before
    matching it with the place prior."""
    overlap_tau_m: float = 0.3
    """`model: overlap`: a ray agrees with the map when its residual is within this, in m (also the
    model's inlier distance)."""
    overlap_sigma: float = 0.1
    """`model: overlap`: σ_o, a share of the rays: the log-likelihood of an agreeing share a is
    −½ ((1 − a) / σ_o)²."""
    histogram_bins: int = 50
    """`model: histogram`: bins of the range histograms, evenly over [0, `max_range_m`)."""
    histogram_sigma: float = 0.05
    """`model: histogram`: σ_h, as a share of the histogram's range: the log-likelihood of the Wasserstein
    distance W between the measured and the rendered histogram is −½ (W / σ_h)²."""
    field_voxel_m: float = 0.1
    """`model: likelihood_field`: voxel size in m of the map's surface voxels that beam ends are scored
    against."""
    field_sigma_m: float = 0.2
    """`model: likelihood_field`: σ in m of the Gaussian on a beam end's distance to the nearest surface
    voxel."""
    field_weight: float = 20.0
    """`model: likelihood_field`: a factor: log-likelihood = weight · mean per-ray log-likelihood, so the
    scan weighs as much as this many independent rays."""


@dataclass
class ConvergenceSettings:
    """When a global search has converged, and how the search keeps its hypotheses (clusters of
    particles) until then (`rangemcl.localization.hypotheses`)."""

    method: str = "hypotheses"
    """The global search and its convergence rule: `hypotheses` (a cloud of particles spread over the map,
    a sequential test on its clusters), `tiles` (the paper's rule: all particles within `tiles` map
    tiles) or `prior` (experimental: a few dozen hypotheses born from the place prior's best places for
    each scan, each searched on a local grid rendered planar about it, and the same sequential test;
    `rangemcl.localization.prior_search`)."""
    tiles: int = 1
    """`method: tiles`: converged when all particles lie in at most this many map tiles (and 95 % of them
    within `max_radius_m`)."""
    max_radius_m: float = 10.0
    """`method: tiles`: radius in m around the estimate that must also hold 95 % of the particles."""
    compact_radius_m: float = 5.0
    """Radius in m. `method: tiles`: a cloud whose 95 % radius is within it counts as converged even across
    a tile border; `method: hypotheses`: the winner's 95 % weight radius must be within it."""
    cluster_m: float = 3.0
    """`method: hypotheses`: cell size in m; particles in touching cells of this size form one cluster
    (one hypothesis)."""
    margin_nats: float = 6.0
    """`method: hypotheses`: evidence margin in nats: the leader's log weight share must beat the best
    rival's by this before the search converges."""
    separation_m: float = 5.0
    """Distance in m beyond which a cluster is a rival of the leader: a satellite nearer on the same street
    is the same place. The recovery uses it too: its second opinion's places lie farther than this from
    the estimate, and a better place confirms the last one when it is found within this of where that
    one moved."""
    min_inliers: float = 0.6
    """`method: hypotheses`: share in [0, 1]: the winner's best particle must also fit at least this share
    of the structure rays (models with an inlier share), so that a place that merely fits less badly than
    the rest does not win."""
    min_distance_m: float = 8.0
    """`method: hypotheses`: distance in m the car must have driven with the same leader before the search
    converges: a look-alike street fits for a stretch, not for ever."""
    min_cluster_particles: int = 20
    """`method: hypotheses`: particles each surviving cluster keeps at resampling, at least, so that a
    hypothesis is dropped by the evidence against it, not by sampling."""
    prune_nats: float = 15.0
    """`method: hypotheses`: clusters whose log weight share lies this many nats below the leader's are
    dropped at resampling."""
    max_clusters: int = 150
    """`method: hypotheses`: at most this many clusters (those of the largest shares) are kept at
    resampling."""
    kld_epsilon: float = 0.05
    """KLD-sampling bound (Fox, 2003) while searching: the particle count keeps the KL divergence between
    the sampled and the true posterior below this, in nats (smaller: more particles)."""
    kld_bin_xy_m: float = 2.0
    """Bin size in m, in x and y, of the occupied bins that the KLD bound counts."""
    kld_bin_yaw_deg: float = 15.0
    """Bin size in degrees of yaw of the occupied bins that the KLD bound counts."""
    min_search_particles: int = 1000
    """The search keeps at least this many particles whatever the KLD bound says."""
    polish_hypotheses: int = 16
    """`method: hypotheses`: while searching, the heaviest this many hypotheses (a cluster's particles in
    one 30-degree sector of yaw) get a dense local grid search around their best particle on each scan
    (a coarse grid of ±2 m and ±8 degrees on every third ray, then a fine one). 0: no polish."""
    polish_keep: int = 8
    """`method: hypotheses`: the best this many poses (at least 1) of each polished hypothesis's fine grid
    join the cloud. The range likelihood is sharply peaked, so without the polish a place is judged by
    particles off its peak; more poses hold the peak's neighbourhood too, at the cost of a larger cloud."""
    challenge_top: int = 100
    """`method: hypotheses`: before the search converges, the place prior's best this many (cell, yaw)
    places for the scan challenge the leader (those farther than `separation_m` from it), and through the
    recovery's probation after it converged (`recovery.probation_updates`) they challenge the converged
    pose: a place that explains the recent scans better reopens the search, the converged cloud and that
    place each a hypothesis with the weight its evidence gives it. The test's margin is measured against
    the rivals the cloud holds; a look-alike that the cloud never drew, or lost while its particles lay
    off its likelihood's peak, is no rival to it, and a leader can win by many nats over places that were
    never its match. 0: no challenge (the method of version 0.17 and before)."""
    challenge_places: int = 16
    """`method: hypotheses`: the best this many distinct challengers (3 m apart) are searched around
    with the polish's grids, as the leader is, and compared with it over the recent scans
    (`challenge_updates`). One within `margin_nats` of the leader (or better) joins the cloud as a
    hypothesis of its own, with the weight that evidence gives it, and the search goes on. 0: no
    challenge."""
    challenge_updates: int = 100
    """`method: hypotheses`: the challenge's evidence: the log-likelihood summed over this many updates'
    scans (those since the search began, if fewer), each place moved back along the odometry to each of
    them; the same measure for the leader and every challenger, so that it does not depend on how many
    particles a place holds or how near its peak they lie. It should reach back as far as the search
    does: a challenger is judged by these scans alone, and a leader that beats a look-alike by little
    per scan needs many of them to beat it by `margin_nats` (the scans are kept in memory, a few kB
    each)."""


@dataclass
class RecoverySettings:
    """When a converged filter declares itself lost and searches again: a watch on its evidence raises a
    suspicion, and a second opinion from the place prior tests it (`rangemcl.localization.lost`)."""

    enabled: bool = True
    """Watch whether the converged filter is lost; false: it never relocalizes (the paper's filter)."""
    signal: str = "inliers"
    """What the watch follows: `inliers` (the best particle's inlier share, i.e. of its rays within 0.3 m
    of the map among those not measured far beyond it, against its running median) or `residual` (the
    best particle's mean residual against its running median and the floor)."""
    inlier_factor: float = 0.5
    """`signal: inliers`: an update is bad when the best inlier share falls below this factor × its
    running median."""
    inlier_residual_factor: float = 0.75
    """`signal: inliers`: an update is also bad when the inlier share falls below this factor × its
    median while the best residual is above `inlier_residual_jump` × its own median (and the floor)."""
    inlier_residual_jump: float = 3.0
    """`signal: inliers`: factor over the best residual's running median beyond which the milder
    `inlier_residual_factor` applies."""
    min_residual_m: float | None = None
    """Floor of the residual watch, in the model's badness units (m for the range model): a best residual
    counts as high only above it (`signal: residual`, and `inlier_residual_jump`). `None`: the model's own
    floor (0.3 m for the range model)."""
    factor: float = 2.0
    """`signal: residual`: an update is bad when the best residual exceeds this factor × its median over
    the recent good converged updates (and the floor)."""
    updates: int = 5
    """Bad updates in a row that raise a suspicion (which is lost at once when no second opinion can be
    asked)."""
    history: int = 50
    """Good converged updates remembered for the running medians."""
    second_opinion: bool = True
    """Test each suspicion against the place prior: it is lost only when one of the prior's best places
    for the scan explains it clearly better than the filter's own cloud, else the alarm is vetoed (the
    world changed, not the place). False: the watch alone decides."""
    opinion_top: int = 100
    """Places scored by each second opinion: the prior's best this many (cell, yaw) candidates for the
    scan, those within `convergence.separation_m` of the estimate left out."""
    opinion_per_place: int = 16
    """Particles scored on each of those places, spread evenly over its prior cell and around its aligned
    yaw."""
    polish_places: int = 16
    """Best distinct places (at least 3 m apart) that get a second look around their best particle: the
    search's grids, a coarse one (±2 m, ±8 degrees) on every third ray, then a fine one around its best
    pose. 0: no second look, nor particles around the last better place or in the look at the past."""
    polish_per_place: int = 48
    """Particles drawn around the last better place (moved with the odometry) when it is scored again,
    and in each round of the look at the past (`history_updates`) around a better place."""
    polish_sigma_xy_m: float = 0.6
    """Spread in m (normal, in x and y) of the `polish_per_place` particles; the look at the past takes
    three rounds, each around the best so far with half the last spread."""
    polish_sigma_yaw_deg: float = 3.0
    """Spread in degrees of yaw of the `polish_per_place` particles (as `polish_sigma_xy_m`)."""
    doubt_inlier_gain: float = 0.25
    """At an update in doubt outside a suspicion and the probation: the inlier share a better place must
    gain, in [0, 1]. Stricter than `opinion_inlier_gain`: in a changed street the true pose fits less
    well, and a distant place's second look can beat it by the usual gain."""
    opinion_inlier_gain: float = 0.15
    """A place is better when its inlier share over the far rays is higher by at least this share (and its
    residual lower)."""
    opinion_badness_ratio: float = 0.7
    """For models without an inlier share: a place is better when its badness is below this factor × the
    filter's."""
    saturated_badness_ratio: float | None = 0.75
    """Where the filter's inlier share leaves no room for the gain (above 1 − gain: a sensor whose far rays
    nearly all fit at a wrong place as at the true one), a place with as many inliers (within 0.02) and a
    badness below this factor × the filter's is better as well. In (0, 1); `None`: off."""
    history_updates: int = 30
    """A better place must also explain the recent past: its mean inlier share over the far rays of this
    many previous updates' scans (moved back along the odometry) must reach the filter's best particle's
    less `history_margin`. A street that changed since the mapping drive fits the true pose badly now but
    not over the past. The look leaves out the scans of the current suspicion (a vehicle alongside that
    hides the far rays at the true pose would otherwise let a distant place fit that past nearly as
    well), and is taken in the probation too (without it a correct convergence can be called lost by a
    look-alike soon after). 0: off."""
    history_margin: float = 0.05
    """Share in [0, 1] by which a better place may fit the past worse than the filter's best particle and
    still count as better."""
    history_min_inliers: float = 0.5
    """The look at the past is taken only while the filter's best particle still fits at least this share
    of the far rays, in [0, 1]: below it the car rather jumped (a kidnap) than the street changed, and the
    past would hold a true new place back."""
    opinion_min_range_m: float = 5.0
    """The second opinion compares only the rays measured at least this far, in m: near rays, above all
    those on a vehicle alongside, fit some wall almost anywhere and let a far-off place fit better than the
    true one."""
    max_vetoed_updates: int = 30
    """A suspicion lasting this many updates is lost all the same, so that a true place missing from the
    prior cannot pin the filter to a wrong one for ever."""
    probation_updates: int = 10
    """After each convergence of a search, a second opinion at each of this many updates, suspicious or
    not: a wrong convergence that fits nearly as well as the truth raises no signal. With the prior search
    (`convergence.method: prior`) the search goes on beside the tracking for these updates instead, its
    rivals searched and weighed as before the convergence. 0: no probation."""
    probation_hits: int = 2
    """Outside a suspicion (in the probation, or at updates in doubt): lost when the second opinion finds
    a consistent better place this many times in a row; in the prior search's probation, undone when one
    rival leads the converged place at this many updates in a row."""
    opinion_hits: int = 2
    """In a suspicion: lost when the second opinion finds a better place this many times in a row, each
    where the last one moved with the odometry (within `convergence.separation_m`). That place is judged
    first and confirmed while it stays better, even where another fits a little more, so that a
    look-alike does not restart the count."""
    opinion_max_misses: int = 2
    """Updates without a better place that the count of confirmations survives in between (the rival moves
    on with the odometry meanwhile); one more drops it."""
    doubt_ratio: float = 0.8
    """An update is in doubt when its inlier share is below this factor × its running level: such an
    update is not refined and gets a second opinion, not only in a suspicion or the probation (a wrong
    place often fits later scans only partly, without falling as low as the watch's limit). Higher: more
    opinions asked (each costs a place prior match and a second look), and fewer updates refined."""


@dataclass
class RefineSettings:
    """Scan-to-mesh refinement of a converged filter's pose: point-to-plane Gauss-Newton of the update's
    rays against the mesh, taken when it lies within the cloud's own spread
    (`rangemcl.localization.refine`)."""

    enabled: bool = True
    """Align each converged update's rays to the mesh and move the cloud by the correction; false: the
    pose is where the particles put it."""
    iterations: int = 5
    """Gauss-Newton steps at most, each re-casting the rays."""
    max_residual_m: float = 0.5
    """A ray takes part when its measured range is within this, in m, of the map's surface along it."""
    huber_m: float = 0.1
    """Huber threshold in m of the point-to-plane residual: larger residuals weigh less."""
    min_inliers: int = 30
    """Rays that must take part, at least (in rays); with fewer there is no refinement."""
    min_information: float = 10.0
    """Directions (in x, y and yaw scaled by `lever_m`) whose information, the sum of the rays' squared
    unit Jacobians, is below this are left where the particles put them (such as along a street of
    parallel walls)."""
    lever_m: float = 10.0
    """Distance in m at which yaw is compared with translation (the scan's typical range): a radian of yaw
    counts as this many metres."""
    min_incidence: float = 0.2
    """Rays meeting their surface at an incidence |cos| below this (grazing) take no part; in [0, 1]."""
    min_hit_height_m: float | None = 2.0
    """Rays hitting the map lower than this, in m above the ground, take no part (parked cars and people
    change between drives), unless fewer than `min_inliers` rays hit higher. `None`: every ray."""
    all_heights_updates: int = 10
    """Updates after a search declares convergence (or after an approximate start pose) in which rays of
    every height take part: the cloud's place along a street may still be off by decimetres that only low
    surfaces fix."""
    gate_m: float = 0.3
    """A correction is taken when its shift is within this, in m, plus twice the cloud's spread in x and y
    (and its turn within `gate_deg`); else it is refused and counted."""
    gate_deg: float = 1.0
    """A correction's turn must be within this, in degrees, plus twice the cloud's yaw spread."""
    weak_information: float | None = 25.0
    """Directions with information from `min_information` up to this move at most `weak_step_m` per update
    (a larger step along them is left out): a few rays on one low surface across a street, as an 8-beam
    sensor sees it, would otherwise pull the pose along the street. `None`: no such band."""
    weak_step_m: float = 0.1
    """Largest step in m (yaw scaled by `lever_m`) taken along a weakly constrained direction per update."""


@dataclass
class InitSettings:
    """Where global localization puts its particles: the drivable area, the place prior, and the fresh
    prior particles injected while the search runs."""

    drive_radius_m: float = 6.0
    """With a map that keeps its mapping drive: particles are spread over the measured ground within this,
    in m, of the drive, with yaw along it. 0 (or a map without a drive): all measured ground, uniform yaw."""
    heading_sigma_deg: float = 15.0
    """Standard deviation in degrees of the spread's yaw around the drive's heading (either way)."""
    uniform_yaw_share: float = 0.25
    """Share in [0, 1] of the spread's particles that get uniform yaw even where the drive gives a
    heading."""
    place_prior: bool = True
    """Use the place prior (`rangemcl.localization.place_prior`): particles drawn where the scan's profile
    fits and injected while searching; the recovery's second opinion needs it too."""
    prior_share: float = 0.7
    """Share in [0, 1] of a global spread redrawn at its first update from the prior's best places for
    that scan; the rest stays uniform over the drivable area, so that no place is excluded."""
    prior_top: int = 300
    """The prior's best (cell, yaw) candidates that the first draw picks from (at most 2 % of its cells,
    at least 20)."""
    prior_cell_m: float = 2.0
    """Grid spacing in m of the place prior over the drivable area; part of the stored prior's key, so a
    new value renders a new prior."""
    prior_yaw_sigma_deg: float = 2.0
    """Yaw spread in degrees (normal) of particles drawn around a candidate's aligned yaw, here and in the
    second opinion."""
    prior_profile_returns: int = 1
    """Returns a bin of a scan's place-prior profile needs: the bin takes the nearest distance at which
    this many returns lie within one surface's spread (10 % of the distance, at least 0.2 m), and a bin
    without such a group is unknown. 1: the nearest return decides (any single one); 3: scattered spurious
    returns (rain droplets or dust near the sensor, mixed pixels at depth edges) no longer set a bin unless
    three of them fall together, however many pulses the sensor fires per bin, while a surface returns
    several neighbouring pulses in each 1-degree bin (every preset fires at least 5 per degree and ring)."""
    prior_skip_zero_intensity: bool = False
    """Leave out of the scans matched with the place prior the returns that report zero intensity, in a
    scan that reports intensity at all (some return above zero). Fog, rain and dust echo weaker than any
    surface: on a calibrated scale (Velodyne's and Ouster's reflectivity, simbed's realistic sensor) they
    report zero, where a surface reports at least a few per cent; in fog of 200 m visibility they are most
    of a scan's returns and every direction's nearest. A scan of the ideal simulated sensor (every
    intensity zero) keeps every return. The weighing's rays are not affected."""
    beam_prior: bool = True
    """A scan with nothing in the prior's high band (a sensor whose beams all point below the horizon,
    such as an 8-beam one) is matched with a prior of the sensor's own top beam instead of the low band,
    where parked cars hide the facades."""
    inject_share: float = 0.05
    """While searching: fresh particles drawn from the prior's best places for each update's scan, as a
    share in [0, 1] of the cloud, which they also take of the weight together; 0: none."""
    inject_top: int = 30
    """The prior's best places for the scan that the fresh particles are drawn from (at most 2 % of its
    cells, at least 20)."""
    inject_below_share: float = 0.9
    """Injection runs only while no hypothesis holds more than this share of the weight, in [0, 1]
    (1: always). The injected weight is the prior odds the search gives a place it has not tested yet,
    and while injected it caps the sequential test: a rival re-injected every update at weight w
    (`inject_share`), fitting each scan rho times as well as the leader, holds about w / places / (1 − rho)
    of the weight. Lower: the cap is lifted sooner, and a place the prior offers late is missed sooner."""


@dataclass
class LocalizerSettings:
    """The localizer's settings, the YAML of `rangemcl localize --config`: one section per part of the
    filter, and the sensor's height and the map's memory budget."""

    particles: ParticleSettings = field(default_factory=ParticleSettings)
    """Particle counts, resampling, roughening and the pose estimate."""
    motion: MotionSettings = field(default_factory=MotionSettings)
    """The odometry motion model, when to update, and the odometry's online calibration."""
    observation: ObservationSettings = field(default_factory=ObservationSettings)
    """The observation model and the rays cast per particle."""
    convergence: ConvergenceSettings = field(default_factory=ConvergenceSettings)
    """When a global search has converged, and its hypotheses until then."""
    recovery: RecoverySettings = field(default_factory=RecoverySettings)
    """When a converged filter is lost: the watch and the place prior's second opinion."""
    refine: RefineSettings = field(default_factory=RefineSettings)
    """Scan-to-mesh refinement of the converged pose."""
    init: InitSettings = field(default_factory=InitSettings)
    """Where a global search spreads its particles, and the place prior."""
    sensor_height_m: float | None = None
    """The sensor's mounting height in m above the ground: it places each particle's sensor over the map's
    ground and splits road from structure. `None`: the sequence's sensor mount, else the map's metadata,
    else 1.73 (KITTI)."""
    map_memory_mb: float | None = None
    """Memory in MB that the localizer may hold of the map (its tiles near the particles,
    `rangemcl.maps.view`); `--map-memory` overrides it. `None`: the whole map when it takes under a
    quarter of the memory available, else that quarter."""

    def check(self, where: str = "settings") -> None:
        """Range checks that the types alone do not give (:data:`_RULES`, then the keys that bound each
        other); an InputError names the key."""
        from rangemcl.localization.models import MODEL_NAMES

        choices = {
            "observation.model": MODEL_NAMES,
            "observation.ray_sampling": RAY_SAMPLINGS,
            "observation.rendering": ("exact", "planar"),
            "motion.calibration": ("estimator", "particles"),
            "convergence.method": ("hypotheses", "tiles", "prior"),
            "recovery.signal": ("inliers", "residual"),
        }
        for key, allowed in choices.items():
            value = self._value(key)
            if value not in allowed:
                expected = (
                    f"'{allowed[0]}' or '{allowed[1]}'"
                    if len(allowed) == 2
                    else f"one of {', '.join(allowed)}"
                )
                raise InputError(f"{where}: {key} {value!r}: expected {expected}")
        for key, rule in _RULES.items():
            value = self._value(key)
            if value is not None and not _RULE_TESTS[rule](value):
                raise InputError(f"{where}: {key} must be {_RULE_TEXT.get(rule, rule)}, got {value}")
        m, o, refine = self.motion, self.observation, self.refine
        if not m.calibration_max_scale >= m.calibration_min_scale:
            raise InputError(
                f"{where}: motion.calibration_max_scale must be >= motion.calibration_min_scale, got "
                f"{m.calibration_max_scale} and {m.calibration_min_scale}"
            )
        weak = refine.weak_information
        if weak is not None and not weak >= refine.min_information:
            raise InputError(
                f"{where}: refine.weak_information must be >= refine.min_information "
                f"({refine.min_information}) or null, got {weak}"
            )
        if o.min_range_m >= o.max_range_m:
            raise InputError(f"{where}: observation.min_range_m must be below observation.max_range_m")

    def _value(self, key: str):
        """The value of a dotted key (``section.name``, or a top-level name)."""
        section, _, name = key.rpartition(".")
        return getattr(getattr(self, section) if section else self, name)


# The range rule of each numeric key that its type alone does not give (LocalizerSettings.check); a key
# whose value is None (an optional setting switched off) is not checked.
_RULES: dict[str, str] = {
    **dict.fromkeys(
        (
            "particles.global_count",
            "particles.converged_count",
            "particles.tracking_count",
            "observation.sigma_m",
            "observation.rays",
            "observation.margin_m",
            "observation.max_range_m",
            "observation.tall_m",
            "observation.overlap_tau_m",
            "observation.overlap_sigma",
            "observation.histogram_bins",
            "observation.histogram_sigma",
            "observation.field_voxel_m",
            "observation.field_sigma_m",
            "observation.field_weight",
            "observation.cap_m",
            "observation.cap_beyond_m",
            "observation.cap_short_m",
            "observation.movable_height_m",
            "observation.vehicle_length_m",
            "convergence.tiles",
            "convergence.cluster_m",
            "convergence.min_cluster_particles",
            "convergence.max_clusters",
            "convergence.kld_epsilon",
            "convergence.kld_bin_xy_m",
            "convergence.kld_bin_yaw_deg",
            "convergence.min_search_particles",
            "convergence.polish_keep",
            "recovery.updates",
            "recovery.history",
            "recovery.opinion_top",
            "recovery.opinion_per_place",
            "recovery.max_vetoed_updates",
            "recovery.probation_hits",
            "recovery.opinion_hits",
            "recovery.opinion_badness_ratio",
            "recovery.opinion_min_range_m",
            "recovery.doubt_ratio",
            "recovery.min_residual_m",
            "init.prior_top",
            "init.prior_profile_returns",
            "init.prior_cell_m",
            "init.inject_top",
            "motion.odometry_scale",
            "motion.calibration_window_m",
            "motion.calibration_window_s",
            "motion.calibration_outlier_m",
            "motion.calibration_outlier_deg",
            "motion.calibration_min_scale",
            "refine.iterations",
            "refine.max_residual_m",
            "refine.huber_m",
            "refine.min_inliers",
            "refine.lever_m",
            "refine.min_hit_height_m",
            "sensor_height_m",
            "map_memory_mb",
        ),
        "> 0",
    ),
    **dict.fromkeys(
        (
            "particles.tracking_sigma_xy_m",
            "particles.tracking_sigma_yaw_deg",
            "particles.jitter_xy_m",
            "particles.jitter_yaw_deg",
            "particles.global_jitter_xy_m",
            "particles.global_jitter_yaw_deg",
            "motion.update_distance_m",
            "motion.update_angle_deg",
            "motion.rot_per_rot",
            "motion.rot_per_trans",
            "motion.trans_per_trans",
            "motion.trans_per_rot",
            "motion.calibration_prior_m",
            "motion.calibration_prior_s",
            "motion.calibration_settle_updates",
            "motion.calibration_sigma_scale",
            "motion.calibration_sigma_bias_deg_s",
            "motion.calibration_walk_scale",
            "motion.calibration_walk_bias_deg_s",
            "observation.min_range_m",
            "convergence.max_radius_m",
            "convergence.compact_radius_m",
            "convergence.margin_nats",
            "convergence.min_distance_m",
            "convergence.prune_nats",
            "convergence.polish_hypotheses",
            "convergence.challenge_top",
            "convergence.challenge_places",
            "convergence.separation_m",
            "recovery.factor",
            "recovery.inlier_factor",
            "recovery.inlier_residual_factor",
            "recovery.inlier_residual_jump",
            "recovery.opinion_inlier_gain",
            "recovery.doubt_inlier_gain",
            "recovery.probation_updates",
            "recovery.polish_places",
            "recovery.polish_per_place",
            "recovery.polish_sigma_xy_m",
            "recovery.polish_sigma_yaw_deg",
            "recovery.opinion_max_misses",
            "init.drive_radius_m",
            "init.heading_sigma_deg",
            "init.prior_yaw_sigma_deg",
            "refine.all_heights_updates",
            "refine.min_information",
            "refine.gate_m",
            "refine.gate_deg",
            "refine.weak_step_m",
            "refine.min_incidence",
        ),
        ">= 0",
    ),
    **dict.fromkeys(
        (
            "recovery.history_margin",
            "recovery.history_min_inliers",
            "init.prior_share",
            "init.inject_share",
            "init.inject_below_share",
            "init.uniform_yaw_share",
            "convergence.min_inliers",
            "observation.ground_share",
            "observation.tall_share",
        ),
        "in [0, 1]",
    ),
    "particles.resample_neff_ratio": "in (0, 1]",
    "particles.estimate_best_share": "in (0, 1]",
    "recovery.saturated_badness_ratio": "in (0, 1)",
    "recovery.history_updates": "an integer >= 0",
    "convergence.challenge_updates": "an integer >= 0",
    "motion.gyro_bias_deg_s": "finite",
}
_RULE_TESTS = {
    "> 0": lambda v: math.isfinite(v) and v > 0,
    ">= 0": lambda v: math.isfinite(v) and v >= 0,
    "in [0, 1]": lambda v: math.isfinite(v) and 0 <= v <= 1,
    "in (0, 1]": lambda v: math.isfinite(v) and 0 < v <= 1,
    "in (0, 1)": lambda v: math.isfinite(v) and 0 < v < 1,
    "an integer >= 0": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    "finite": lambda v: math.isfinite(v),
}
_RULE_TEXT = {"in (0, 1)": "in (0, 1) or null"}

"""Experiment pipelines shared by the ``train/`` scripts, the demo and the tutorials.

Peg-in-hole (:mod:`torchcontact.envs`): :func:`run_round` trains (or evaluates) a
:class:`~torchcontact.rl.DynaQ` agent on rounds of batched episodes with
:class:`PotentialShaping` and records the steps (:class:`PegLearning` holds the settings that
learn the task); :func:`evaluate` executes the learned policy under uncertainty (oracle, raw
observation, QMDP over the RBPF belief with :func:`qmdp_actions`, QMDP that first probes by
touch where the camera is blind (:func:`probe_presses`, :func:`lateral_spread`), neural Q on
:func:`belief_features`), with :class:`QLookup` mapping manipulation-state ids to Q rows.
Scripts check their arguments with :func:`check_int`, :func:`check_real`, :func:`check_choice`
and :func:`check_name` before any work, get a new run folder or the one to resume with
:func:`open_run`, log to it with :class:`RunLog` (arguments, ``charts/SPS``) and write
checkpoints atomically with :func:`save_checkpoint`.

Triangle grasp (:mod:`torchcontact.sim`): :func:`grasp_trials` simulates grasps of a triangle
that the camera loses sight of, with tactile readings and the mode table of training
rollouts (:class:`TriangleGrasp` holds the settings); :func:`run_estimators` tracks them with
the contact RBPF (:func:`grasp_contact_model`), the simulator particle filter, an EKF and held
vision; :func:`evaluate_tracking`, :func:`grasp_summary` and :func:`tracking_table` score them
and :func:`plot_grasp_snapshots`, :func:`plot_tracking_errors` and :func:`plot_mode_timeline`
draw them. :func:`write_grasp_logs` writes the trials as run logs (:mod:`torchcontact.logs`)
and :func:`replay` runs an estimator over logs, scored as in the experiment.

BarrettHand box grasp (:mod:`torchcontact.sim` with robots): :func:`box_trials` simulates the
WAM carrying the BarrettHand to a box that it grasps, tips over or pushes (:class:`BarrettBoxGrasp`
holds the settings, :class:`BoxTrials` the truth and measurements: pair contact states,
camera, tactile pads of :func:`hand_pads`, the tip-over step); :func:`run_box_estimators`
tracks them with the spatial contact RBPF (:func:`box_contact_model`), the simulator particle
filter, an EKF on SE(3) and the held camera pose; :func:`box_tracking_metrics` and
:func:`box_tracking_table` score them and :func:`plot_box_errors`,
:func:`plot_box_snapshots` and :func:`plot_box_states` draw them.

Fitting (:mod:`torchcontact.filters`): :func:`sliding_logs` simulates boxes sliding to a stop
under a noisy camera (:class:`SlidingFit` holds the settings), :func:`sliding_evidence` is the
contact RBPF's evidence of friction and camera noise over them, and :data:`FITTERS` maximize
it by gradient, over a grid and by CMA-ES. :func:`grasp_fit_logs` simulates trials of the
triangle grasp with a launched triangle (:class:`GraspFit` holds the settings) and
:func:`grasp_fit_evidence` is the grasp RBPF's evidence of the ground friction and camera
noise over them.

Many seeds (``train/sweep.py``): :func:`seed_statistics` is the mean, range and Student-t
interval of one metric over seeds (:class:`SeedStatistics`); :func:`aggregate_seeds` gives it
for every setting and metric (:class:`SweepRow`), from the scalars of each run's result
(:func:`scalar_metrics`); :func:`statistics_table` and :func:`write_statistics` write the
table as Markdown, JSON and CSV.
"""

from torchcontact._checks import check_choice, check_int, check_name, check_real
from torchcontact.experiments._barrett_box import (
    BOX_PAIRS,
    PAD_LINKS,
    TIP_ANGLE,
    BarrettBoxGrasp,
    BoxTrials,
    approach_plan,
    barrett_box_scene,
    barrett_member,
    box_tilt,
    box_trials,
    first_tip_step,
    grasp_phases,
    hand_pads,
    pad_triggers,
    pair_slots,
    pair_states,
    palm_ik,
)
from torchcontact.experiments._barrett_box_estimators import (
    BOX_METHODS,
    RBPF_METHODS,
    BoxEstimatorRuns,
    box_contact_model,
    box_filter_scene,
    box_prior,
    joint_motion,
    run_box_camera,
    run_box_ekf,
    run_box_estimators,
    run_box_pf,
    run_box_rbpf,
    score_box_estimators,
)
from torchcontact.experiments._barrett_box_metrics import (
    TIP_TOLERANCE,
    box_tracking_metrics,
    box_tracking_table,
    geodesic_angle,
)
from torchcontact.experiments._barrett_box_plots import (
    plot_box_errors,
    plot_box_snapshots,
    plot_box_states,
)
from torchcontact.experiments._checkpoint import (
    ARGUMENTS,
    CHECKPOINT,
    LOCATION,
    RunLog,
    load_checkpoint,
    new_run_dir,
    open_run,
    read_checkpoint,
    save_checkpoint,
)
from torchcontact.experiments._friction_fit import (
    FIT_METHODS,
    FITTERS,
    FitOutcome,
    FitSearch,
    SlidingFit,
    SlidingLogs,
    box_scene,
    sliding_evidence,
    sliding_logs,
)
from torchcontact.experiments._grasp_fit import (
    GraspFit,
    GraspFitLogs,
    camera_std,
    grasp_fit_evidence,
    grasp_fit_logs,
    grasp_fit_scene,
    launched_grasps,
)
from torchcontact.experiments._grasp_logs import (
    FINGER_JOINTS,
    Replay,
    grasp_run_logs,
    grasp_trials_from_logs,
    logged_settings,
    replay,
    write_grasp_logs,
)
from torchcontact.experiments._peg_execution import (
    NUM_BELIEF_FEATURES,
    SETTINGS,
    Evaluation,
    Setting,
    belief_features,
    evaluate,
    evaluate_settings,
    qmdp_actions,
    raw_poses,
    results_table,
)
from torchcontact.experiments._peg_learning import (
    PegLearning,
    PotentialShaping,
    RoundResult,
    round_seed,
    run_round,
)
from torchcontact.experiments._peg_probing import (
    PRESS,
    PROBE_THRESHOLD,
    bottom_sides,
    bottom_touch,
    lateral_spread,
    probe_presses,
    shift_actions,
)
from torchcontact.experiments._q_lookup import QLookup
from torchcontact.experiments._sweep import (
    STATISTICS_COLUMNS,
    SeedStatistics,
    SweepRow,
    aggregate_seeds,
    scalar_metrics,
    seed_statistics,
    statistics_records,
    statistics_table,
    write_statistics,
)
from torchcontact.experiments._triangle_grasp import (
    FILTER_SEED_OFFSETS,
    GRASP_METHODS,
    EstimatorRuns,
    GraspTrials,
    Timing,
    TriangleGrasp,
    calibrate_pf,
    evaluate_tracking,
    grasp_contact_model,
    grasp_controls,
    grasp_mode_table,
    grasp_schedule,
    grasp_summary,
    grasp_tactile_readings,
    grasp_trials,
    min_vertex_height,
    run_ekf,
    run_estimators,
    run_pf,
    run_rbpf,
    run_vision,
    simulate_grasps,
    timed,
    tracking_table,
    triangle_scene,
    triangle_tactile_array,
)
from torchcontact.experiments._triangle_grasp_plots import (
    plot_grasp_snapshots,
    plot_mode_timeline,
    plot_tracking_errors,
)

__all__ = [
    "ARGUMENTS",
    "BOX_METHODS",
    "BOX_PAIRS",
    "CHECKPOINT",
    "FILTER_SEED_OFFSETS",
    "FINGER_JOINTS",
    "FITTERS",
    "FIT_METHODS",
    "GRASP_METHODS",
    "LOCATION",
    "NUM_BELIEF_FEATURES",
    "PAD_LINKS",
    "PRESS",
    "PROBE_THRESHOLD",
    "RBPF_METHODS",
    "SETTINGS",
    "STATISTICS_COLUMNS",
    "TIP_ANGLE",
    "TIP_TOLERANCE",
    "BarrettBoxGrasp",
    "BoxEstimatorRuns",
    "BoxTrials",
    "EstimatorRuns",
    "Evaluation",
    "FitOutcome",
    "FitSearch",
    "GraspFit",
    "GraspFitLogs",
    "GraspTrials",
    "PegLearning",
    "PotentialShaping",
    "QLookup",
    "Replay",
    "RoundResult",
    "RunLog",
    "SeedStatistics",
    "Setting",
    "SlidingFit",
    "SlidingLogs",
    "SweepRow",
    "Timing",
    "TriangleGrasp",
    "aggregate_seeds",
    "approach_plan",
    "barrett_box_scene",
    "barrett_member",
    "belief_features",
    "bottom_sides",
    "bottom_touch",
    "box_contact_model",
    "box_filter_scene",
    "box_prior",
    "box_scene",
    "box_tilt",
    "box_tracking_metrics",
    "box_tracking_table",
    "box_trials",
    "calibrate_pf",
    "camera_std",
    "check_choice",
    "check_int",
    "check_name",
    "check_real",
    "evaluate",
    "evaluate_settings",
    "evaluate_tracking",
    "first_tip_step",
    "geodesic_angle",
    "grasp_contact_model",
    "grasp_controls",
    "grasp_fit_evidence",
    "grasp_fit_logs",
    "grasp_fit_scene",
    "grasp_mode_table",
    "grasp_phases",
    "grasp_run_logs",
    "grasp_schedule",
    "grasp_summary",
    "grasp_tactile_readings",
    "grasp_trials",
    "grasp_trials_from_logs",
    "hand_pads",
    "joint_motion",
    "lateral_spread",
    "launched_grasps",
    "load_checkpoint",
    "logged_settings",
    "min_vertex_height",
    "new_run_dir",
    "open_run",
    "pad_triggers",
    "pair_slots",
    "pair_states",
    "palm_ik",
    "plot_box_errors",
    "plot_box_snapshots",
    "plot_box_states",
    "plot_grasp_snapshots",
    "plot_mode_timeline",
    "plot_tracking_errors",
    "probe_presses",
    "qmdp_actions",
    "raw_poses",
    "read_checkpoint",
    "replay",
    "results_table",
    "round_seed",
    "run_box_camera",
    "run_box_ekf",
    "run_box_estimators",
    "run_box_pf",
    "run_box_rbpf",
    "run_ekf",
    "run_estimators",
    "run_pf",
    "run_rbpf",
    "run_round",
    "run_vision",
    "save_checkpoint",
    "scalar_metrics",
    "score_box_estimators",
    "seed_statistics",
    "shift_actions",
    "simulate_grasps",
    "sliding_evidence",
    "sliding_logs",
    "statistics_records",
    "statistics_table",
    "timed",
    "tracking_table",
    "triangle_scene",
    "triangle_tactile_array",
    "write_grasp_logs",
    "write_statistics",
]

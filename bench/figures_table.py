"""The figures `main.py figures` puts on docs/figures.md: name, source, key, target, command.

A source without a `/` is a summary saved under artifacts/bench/ (`summary_name`: the bench, the tags of the
options that change its figures, `-seed<S>`); one with a `/` is a report another command writes.  Adding a
figure is adding a line here; its meaning goes to docs/measurements.md."""

from __future__ import annotations

from bench.figures import Figure as F

PEG = "main.py bench peg-in-hole --trials 50 --seed 1"
PEG_SENSOR = f"{PEG} --force-source sensor"
PEG_TIGHT = f"{PEG} --peg-diameter-mm 21.7"
PEG_TIGHTER = f"{PEG} --peg-diameter-mm 21.75"
COLLISION = "main.py bench collision --seed 57"
PLANNING = "main.py bench planning --paths 20 --seed 7 --json"  # and --seed 9, 13
PLANNING_TORQUE = "main.py bench planning --paths 20 --seed 7 --paths-class torque --json"
PLAN_SRC = "planning"
HAND = "main.py bench hand-guide --seed 7 --json"
MODEL = "main.py bench model --data artifacts/data/wipe/dataset.yaml --model artifacts/models/wipe"
EVAL = "main.py evaluate --data artifacts/data/default/dataset.yaml --out artifacts/eval/default"
EVAL_UR = ("main.py evaluate --robot ur10e --data artifacts/data/ur10e/dataset.yaml --out artifacts/eval/ur10e "
           "--no-curve --lofo")
EVAL_DOC = "artifacts/eval/default/evaluation.json"
EVAL_UR_DOC = "artifacts/eval/ur10e/evaluation.json"
CAL_WIPE = "artifacts/calibration/wipe/calibration.json"
CAL_PEG = "artifacts/calibration/peg/calibration.json"
FAULT = "faults.{}.detection_periods"

FIGURES: tuple[F, ...] = (
    # peg-in-hole, virtual sensor (Kalman + contact map) in the loop; hole moved +-2 mm, tilted +-2 deg
    F("peg-in-hole, virtual sensor: success rate", "peg-in-hole", "success_rate", ">= 0.95", f"{PEG} --json"),
    F("peg-in-hole, virtual sensor: median time (s)", "peg-in-hole", "median_time_s", "<= 15", f"{PEG} --json"),
    F("peg-in-hole, virtual sensor: peak force (N)", "peg-in-hole", "peak_force_n", "<= 80", f"{PEG} --json"),
    F("peg-in-hole, virtual vs F/T: Mx MAE (N m)", "peg-in-hole", "virtual_vs_sensor_mx_mae_nm",
      "<= 0.15 (paper 0.378)",
      f"{PEG} --json"),
    F("peg-in-hole, virtual vs F/T: My MAE (N m)", "peg-in-hole", "virtual_vs_sensor_my_mae_nm",
      "<= 0.15 (paper 0.242)",
      f"{PEG} --json"),
    F("peg-in-hole, virtual vs F/T: Fz MAE (N)", "peg-in-hole", "virtual_vs_sensor_fz_mae_n", "<= 4 (paper 9.438)",
      f"{PEG} --json"),
    F("peg-in-hole, F/T sensor: success rate", "peg-in-hole-sensor", "success_rate", ">= 0.95",
      f"{PEG_SENSOR} --json"),
    F("peg-in-hole, F/T sensor: median time (s)", "peg-in-hole-sensor", "median_time_s", "<= 15",
      f"{PEG_SENSOR} --json"),
    F("peg-in-hole, F/T sensor: peak force (N)", "peg-in-hole-sensor", "peak_force_n", "<= 80",
      f"{PEG_SENSOR} --json"),
    F("peg-in-hole: surveyed vs true hole axis (deg)", "peg-in-hole-sensor", "max_axis_error_deg", "reported",
      f"{PEG_SENSOR} --json"),
    # tight fits (docs/peg.md): 0.1 mm (21.7 mm peg) and 0.05 mm (21.75 mm) diametral clearance
    F("peg-in-hole, 21.7 mm peg, virtual sensor: success rate", "peg-in-hole-d21.7mm", "success_rate", ">= 0.95",
      f"{PEG_TIGHT} --json"),
    F("peg-in-hole, 21.7 mm peg, virtual sensor: median time (s)", "peg-in-hole-d21.7mm", "median_time_s", "<= 20",
      f"{PEG_TIGHT} --json"),
    F("peg-in-hole, 21.7 mm peg, virtual sensor: peak force (N)", "peg-in-hole-d21.7mm", "peak_force_n", "<= 80",
      f"{PEG_TIGHT} --json"),
    F("peg-in-hole, 21.75 mm peg, virtual sensor: success rate", "peg-in-hole-d21.75mm", "success_rate", ">= 0.8",
      f"{PEG_TIGHTER} --json"),
    F("peg-in-hole, 21.75 mm peg, virtual sensor: median time (s)", "peg-in-hole-d21.75mm", "median_time_s",
      "reported", f"{PEG_TIGHTER} --json"),
    F("peg-in-hole, 21.75 mm peg, virtual sensor: peak force (N)", "peg-in-hole-d21.75mm", "peak_force_n", "<= 80",
      f"{PEG_TIGHTER} --json"),
    F("peg-in-hole, 21.7 mm peg, F/T sensor: success rate", "peg-in-hole-sensor-d21.7mm", "success_rate",
      "reported", f"{PEG_TIGHT} --force-source sensor --json"),
    F("peg-in-hole, one run (`./run.sh`): insertion time (s)", "run-peg-in-hole", "insertion_time_s", "<= 15",
      "./run.sh --json"),
    F("peg-in-hole, one run (`./run.sh`): peak force (N)", "run-peg-in-hole", "peak_force_n", "<= 80",
      "./run.sh --json"),
    F("peg-in-hole, one run (`./run.sh`): virtual vs F/T Fz MAE (N)", "run-peg-in-hole", "virtual_vs_sensor_fz_mae_n",
      "<= 2", "./run.sh --json"),
    F("peg-in-hole, one run (`./run.sh`): virtual over F/T peak at touches", "run-peg-in-hole", "touch_peak_ratio",
      "0.5-2", "./run.sh --json"),
    F("peg-in-hole, one run (`./run.sh`): control step compute p99 (ms)", "run-peg-in-hole", "timing.compute_ms_p99",
      "<= 1.0", "./run.sh --json"),
    F("peg-in-hole over the wire: outcome", "run-peg-in-hole-emulated", "outcome", "done",
      "main.py run peg-in-hole --cell emulated --json"),
    # wiping at 60 N
    F("wipe, F/T sensor in the loop: force MAE (N)", "run-wipe-sensor", "force_tracking_mae_n", "<= 2",
      "main.py run wipe --force-source sensor --json"),
    F("wipe, F/T sensor in the loop: force std (N)", "run-wipe-sensor", "force_tracking_std_n", "<= 2",
      "main.py run wipe --force-source sensor --json"),
    F("wipe, virtual sensor: virtual vs F/T Fz MAE (N)", "run-wipe", "virtual_vs_sensor_fz_mae_n",
      "<= 3 (paper 7.995)", "main.py run wipe --json"),
    F("wipe, virtual sensor: force MAE (N)", "run-wipe", "force_tracking_mae_n", "<= 4", "main.py run wipe --json"),
    F("wipe over the wire, F/T sensor: outcome", "run-wipe-emulated-sensor", "outcome", "done",
      "main.py run wipe --cell emulated --force-source sensor --json"),
    F("wipe over the wire, F/T sensor: force MAE (N)", "run-wipe-emulated-sensor", "force_tracking_mae_n", "<= 2",
      "main.py run wipe --cell emulated --force-source sensor --json"),
    # the virtual sensor against the F/T sensor, held-out postures
    F("calibration, wipe tool: Fz MAE (N)", CAL_WIPE, "report.fz_mae_n", "<= 2.5 (paper 9.4)",
      "main.py calibrate --json"),
    F("calibration, wipe tool: Mx MAE (N m)", CAL_WIPE, "report.mx_mae_nm", "<= 0.1 (paper 0.378)",
      "main.py calibrate --json"),
    F("calibration, wipe tool: My MAE (N m)", CAL_WIPE, "report.my_mae_nm", "<= 0.1 (paper 0.242)",
      "main.py calibrate --json"),
    F("calibration, peg tool, Kalman + Jacobian: My MAE (N m)", CAL_PEG, "report.routes.kalman+jacobian.my_mae_nm",
      "<= 0.1", "main.py calibrate --tool peg --json"),
    # collisions: scripted impacts on obstacle plates, 10 simulated minutes of free motion
    F("collision: detection latency p95, rigid plates (ms)", "collision", "detection_latency_ms_p95_rigid",
      "<= 16 (two periods)", f"{COLLISION} --json"),
    F("collision: detection latency median (ms)", "collision", "detection_latency_ms_median", "reported",
      f"{COLLISION} --json"),
    F("collision: impacts missed", "collision", "missed", "none", f"{COLLISION} --json"),
    F("collision: false alarms (per 10 min of free motion)", "collision", "false_alarms", "0",
      f"{COLLISION} --json"),
    F("collision: largest free-motion ratio", "collision", "free_motion_max_ratio", "<= 0.8", f"{COLLISION} --json"),
    F("collision: spring plates, force at detection p95 (N)", "collision", "force_at_detection_n_p95_soft", "<= 140",
      f"{COLLISION} --json"),
    F("collision: spring plates, force at the earliest possible decision p95 (N)", "collision",
      "force_at_first_decision_n_p95_soft", "reported (the 8 ms loop's floor)", f"{COLLISION} --json"),
    F("collision: spring plates, contact peak p95 (N)", "collision", "peak_force_n_p95_soft", "<= 280",
      f"{COLLISION} --json"),
    F("collision: spring plates, spring-side peak p95 (N)", "collision", "spring_peak_n_p95_soft", "reported",
      f"{COLLISION} --json"),
    F("collision: spring plates, contact peak over force at detection p95", "collision",
      "peak_over_detection_p95_soft", "<= 1.3", f"{COLLISION} --json"),
    F("collision: spring plates, spring-side peak over force at detection p95", "collision",
      "spring_peak_over_detection_p95_soft", "reported", f"{COLLISION} --json"),
    F("collision: peak force, rigid plate at 0.25 m/s (N)", "collision", "peak_force_n_rigid_025",
      "reported (150 N is out of reach at 8 ms: docs/collision.md)", f"{COLLISION} --json"),
    F("collision: peak force p95 (N)", "collision", "peak_force_n_p95", "reported", f"{COLLISION} --json"),
    F("collision: peak force max (N)", "collision", "peak_force_n_max", "reported", f"{COLLISION} --json"),
    F("collision: virtual over F/T peak force (median)", "collision", "virtual_peak_ratio", ">= 0.7",
      f"{COLLISION} --json"),
    # faults injected over the wire (real drivers, emulators): control periods from injection to stop
    F("faults: failures", "faults", "failures", "0", "main.py bench faults --json"),
    F("faults: link loss (periods)", "faults", FAULT.format("link_loss"), "<= 2", "main.py bench faults --json"),
    F("faults: stale robot data (periods)", "faults", FAULT.format("stale_robot_data"),
      "<= stale_after_s / period + 3", "main.py bench faults --json"),
    F("faults: late replies (periods)", "faults", FAULT.format("late_replies"), "<= 2",
      "main.py bench faults --json"),
    F("faults: Modbus exceptions (periods)", "faults", FAULT.format("modbus_exceptions"), "<= 2",
      "main.py bench faults --json"),
    F("faults: silent F/T sensor (periods)", "faults", FAULT.format("sensor_silent"),
      "<= max_sensor_invalid_cycles + 2", "main.py bench faults --json"),
    F("faults: garbling F/T sensor (periods)", "faults", FAULT.format("sensor_garbage"),
      "<= max_sensor_invalid_cycles + 2", "main.py bench faults --json"),
    F("faults: late F/T sensor (periods)", "faults", FAULT.format("sensor_late_replies"),
      "<= max_sensor_invalid_cycles + 2", "main.py bench faults --json"),
    # serving the hybrid model, the virtual sensor's step
    F("model: hybrid predict p99 (us)", "model", "hybrid_predict_p99_us", "<= 200", f"{MODEL} --json"),
    F("model: speed-up over stock XGBoost", "model", "speedup", ">= 5", f"{MODEL} --json"),
    F("model: 500k-sample fit (s)", "model", "fit_s", "<= 120", f"{MODEL} --json"),
    F("model: batch throughput (samples/s)", "model", "batch_samples_per_s", ">= 100,000", f"{MODEL} --json"),
    F("virtual sensor: one step p99 (us)", "model", "virtual_sensor_step_p99_us", "<= 300", f"{MODEL} --json"),
    # time-optimal planning with the prepared hybrid model, against the pendant-knob baseline
    F("planning: worst path's time saved vs uniform (%)", "plan", "min_improvement_vs_uniform_pct", ">= 25",
      "main.py plan --json"),
    F("planning: peak torque over its limit", "plan", "max_torque_ratio", "<= 1.0", "main.py plan --json"),
    F("planning: slowest plan (s)", "plan", "max_plan_time_s", "<= 1", "main.py plan --json"),
    # the planning bench: four planners on 3 named + 20 random paths, run on the plant with the collision guard
    # (docs/planning.md); the torque class: short and medium joint 1-3 moves with payloads
    F("planning: ours, median gap closed to the speed-limit bound, random paths", PLAN_SRC,
      "median_gap_closed.random", ">= 0.5", PLANNING),
    F("planning: ours, median gap closed to the speed-limit bound, named paths", PLAN_SRC,
      "median_gap_closed.named", ">= 0.6", PLANNING),
    F("planning: ours / kinematic, median time", PLAN_SRC, "median_time_ratio.model", "reported", PLANNING),
    F("planning, torque class: ours / kinematic, median time", "planning-torque", "median_time_ratio.model",
      "<= 0.8", PLANNING_TORQUE),
    F("planning, torque class: our first runs over a torque limit", "planning-torque", "torque_violations.model",
      "0", PLANNING_TORQUE),
    F("planning: PPO / kinematic, median time", PLAN_SRC, "median_time_ratio.ppo", "report", PLANNING),
    F("planning: uniform / kinematic, median time", PLAN_SRC, "median_time_ratio.uniform", "report", PLANNING),
    F("planning: our first runs over a torque limit", PLAN_SRC, "torque_violations.model", "0", PLANNING),
    F("planning: our paths not validated", PLAN_SRC, "unvalidated_paths.model", "0", PLANNING),
    F("planning: kinematic first runs over a torque limit", PLAN_SRC, "torque_violations.kinematic", "report",
      PLANNING),
    F("planning: our plan time p95 (s)", PLAN_SRC, "plan_time_s_p95.model", "<= 1", PLANNING),
    F("planning: paths where ours <= PPO", PLAN_SRC, "model_vs_ppo.paths_model_not_slower", "all 23", PLANNING),
    F("planning: PPO time saved vs uniform, median (%)", PLAN_SRC, "reduction_vs_uniform_median_pct.ppo",
      "paper ~20", PLANNING),
    F("planning: PPO, one policy per path, trajectory_1 saved (%)", PLAN_SRC,
      "paper_setting.trajectory_1.reduction_vs_uniform_pct", "paper 24.7", PLANNING),
    F("planning: PPO training (s)", PLAN_SRC, "ppo_training_s", "minutes", PLANNING),
    F("planning: our runs stopped by the collision guard", PLAN_SRC, "collision_stops.model", "0", PLANNING),
    # sensorless hand guiding: a simulated hand (800 N/m, 40 N s/m) along a 0.4 m path at 0.1 m/s
    F("hand guiding: path error max (mm)", "hand-guide", "path_error_mm_max", "<= 15", HAND),
    F("hand guiding: hand force max (N)", "hand-guide", "hand_force_n_max", "<= 15", HAND),
    F("hand guiding: drift over 10 s after release (mm)", "hand-guide", "release_drift_mm", "<= 2", HAND),
    F("hand guiding: a push over the limit stops the arm", "hand-guide", "push_stopped", "true", HAND),
    # the simulated cell and the drivers
    F("simulation: real-time factor", "sim", "real_time_factor", ">= 20", "main.py bench sim --json"),
    F("plant: P1 RMSE, J1-3 (N m)", "plant", "p1_rmse_j123_nm", "~10", "main.py bench plant --json"),
    F("plant: ideal P2 RMSE, J1-3 (N m)", "plant", "ideal_p2_rmse_j123_nm", "2-4", "main.py bench plant --json"),
    F("plant: noise RMSE, J1-3 (N m)", "plant", "noise_rmse_j123_nm", "< half of P2",
      "main.py bench plant --json"),
    F("drivers: Modbus cycle median (ms)", "drivers", "modbus_cycle_median_ms", "<= 2",
      "main.py bench drivers --json"),
    F("drivers: serial read median (ms)", "drivers", "serial_read_median_ms", "<= 1",
      "main.py bench drivers --json"),
    # the model lab (J1-3 mean RMSE on held-out trajectories)
    F("model lab, default plant: H1 RMSE (N m)", EVAL_DOC, "mean_rmse_j123.H1", "best of six", f"{EVAL} --json"),
    F("model lab, default plant: P2 / P1", EVAL_DOC, "p2_over_p1", "<= 0.5", f"{EVAL} --json"),
    F("model lab, default plant: H1 / P2", EVAL_DOC, "h1_over_p2", "<= 0.7", f"{EVAL} --json"),
    F("model lab, default plant: D(500k) / P2", EVAL_DOC, "d_large_over_p2", "<= 1", f"{EVAL} --json"),
    F("model lab, default plant: H1 errors within 2 sigma", EVAL_DOC, "uncertainty.H1.within_2_sigma", "~0.95",
      f"{EVAL} --json"),
    F("model lab, UR10e logs: P2 / P1", EVAL_UR_DOC, "p2_over_p1", "<= 0.5", f"{EVAL_UR} --json"),
    F("model lab, UR10e logs: H1 / P2", EVAL_UR_DOC, "h1_over_p2", "<= 0.8", f"{EVAL_UR} --json"),
    F("model lab, UR10e logs: H1 / P2, worst left-out file", EVAL_UR_DOC, "leave_one_file_out.h1_over_p2_worst",
      "<= 0.8", f"{EVAL_UR} --json"),
)

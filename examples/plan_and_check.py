"""Plan the joint commands and tendon tensions that move the pan-tilt arm's
tool along a line (statics), execute the plan in the dynamics to see how
far the real arm would lag behind it, then compensate the lag. The same
calls plan a classic rod (``load_mechanism("tendon_arm")``).

Run: python examples/plan_and_check.py"""

from soft_twin_core.planning import paths
from soft_twin_core.planning import planner as pl
from soft_twin_core.robot.mechanism import load_mechanism

arm = load_mechanism("pan_tilt_arm")
path = paths.line([0.33, -0.03, 0.0], [0.33, 0.03, 0.02], 2.0, sample_period=0.05)
options = pl.PlanOptions(frame="tool")
plan = pl.plan_path(arm, path, options)
print(f"plan: {len(plan.times)} samples, {int(plan.reached.sum())} reached, joints {plan.joint_names}, "
      f"final commands {dict(zip(plan.joint_names, plan.joints[-1].round(4).tolist()))} rad")
tracking = pl.simulate_plan(arm, plan, options, dt=0.005, hold=0.5)
s = tracking.summary()
print(f"dynamics: rms error {1e3 * s['rms_error_m']:.2f} mm, max {1e3 * s['max_error_m']:.2f} mm, "
      f"after a 0.5 s hold {1e3 * s['final_error_m']:.2f} mm")
best, tracked, history = pl.compensate_lag(arm, path, options, iterations=2)
print(f"lag compensated: rms error {1e3 * tracked.summary()['rms_error_m']:.2f} mm "
      f"(iterations: {[round(1e3 * h['rms_error_m'], 2) for h in history]} mm)")

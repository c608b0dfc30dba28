"""Names the command line offers before anything of the flight is loaded (this module imports
nothing, so ``stillbox-bench`` builds its options without the scene sampling)."""

#: the renderers of render.py: a persistent Blender worker, or the analytic depth of raycast.py
RENDERERS = ("blender", "analytic")
#: simulate.FlightConfig.yaw: the camera keeps the straight line's heading, or faces the goal
YAW_MODES = ("goal", "line")
#: simulate.FlightConfig.max_steps: control steps before an episode ends as "timeout"
MAX_STEPS = 300

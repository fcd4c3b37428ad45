# `import sim` sets MUJOCO_GL=egl before any test module imports mujoco.
import sim  # noqa: F401

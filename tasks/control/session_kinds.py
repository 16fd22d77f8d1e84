"""The synthetic squeeze sessions (``signal.session``, ``object.session``) that
:func:`tasks.control.squeeze_signals.synthetic_session` generates; a module of its own so that the pre-flight checks
read it without importing the step (and Prefect with it)."""

SESSION_KINDS: tuple[str, ...] = ("ramp_hold_release", "pulses", "poke", "crush")

"""The glove: the one definition of the hand's fingers (SenseGlove order, thumb first)."""

FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
N_FINGERS: int = len(FINGERS)

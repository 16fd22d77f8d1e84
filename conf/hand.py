"""The glove: the one definition of the hand's fingers (SenseGlove order, thumb first)."""

FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
N_FINGERS: int = len(FINGERS)
# m, the fingertip pad's radius of curvature: the Hertz aspect of the contact patches (eq. 2 force prior) and the
# collider fingers' radius (``mpm.fingers=collider``)
FINGERTIP_PAD_RADIUS: float = 0.01

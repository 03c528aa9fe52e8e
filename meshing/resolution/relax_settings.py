"""The relaxation's settings: the penalties of its soft constraints, its trust region and
its budget of steps (each value's reason beside it)."""

_LOWER_PENALTY = 1e5  # per mm below a lower bound
_SURFACE_PENALTY = 1e4  # per mm out of a surface contact's plane
_SOFT_PENALTY = 1e3  # per mm beyond an upper bound or off parallel (keeps contact classes)
# Per mm of a touching line contact's edge off its partner. Softer than the rest: a chip
# lying flat on one partner cannot always lay an edge exactly on another as well, and the
# surface contact comes first (reference stack, seed 0: at 1e3 twice the surface contacts
# were let go; at 1e4 three chips could not be resolved).
_TOUCHING_PENALTY = 1e2
# Per radian off alignment: as strong as the edge penalty (per mm) at the end of a 10 mm
# lever. At 1e3 a radian (5e1 a millimetre there) the alignment of a chip resting on
# others stalled a few 1e-4 rad short, and was let go as a wedge that thin (reference
# stack, seed 1).
_ALIGN_PENALTY = 1e4
_EDGE_PENALTY = 1e3  # per mm off flush, or of a corner short of its distance from an edge
# Two chips in a shared plane whose outlines cross at less than this are turned (about
# the plane's normal) until their edges are parallel: outlines crossing at a shallow
# angle cut the shared face into a thin wedge, and no tetrahedron on it can be sound.
_ALIGN_DEG = 6.0
_EXTRA_ITERATIONS = 30  # steps given after stuck surface contacts are let go at the end
_EXTENSIONS = 3  # at most this many times
_FLUSH_MM = 0.3  # parallel edges closer than this in a shared plane are made flush
_STEP_MM = 0.1  # trust region per step
_STEP_RAD = 0.01
_ITERATIONS = 80
_CHECKPOINTS = (12, 24, 40)  # steps at which what cannot hold is let go
_STATIONARY = 1 / 64  # a trust region this small: the step has settled (a checkpoint)
_POLISH_STEPS = 5  # at most this many restoring steps when the budget runs out
_POLISH_RADIUS = 1e-4  # their trust region: second-order errors ~1e-11 mm

"""Goal spaces: state -> sub-goal, done(s, g), similarity and images, one per domain."""

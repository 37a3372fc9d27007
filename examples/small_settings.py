"""HhP settings shared by the examples: small buffers and fewer dropout masks, so a demo runs in a minute."""

SMALL_SETTINGS = dict(
    max_subgoal_steps=50,
    learning_starts=500,  # meta-controller warm-up, in primitive steps (beyond the first episode)
    buffer_size=50_000,
    n_masks=100,  # MC-dropout masks of the confidence (paper: 500)
    subpolicy_kwargs=dict(learning_starts=100, buffer_size=20_000, batch_size=64),
    subpolicy_exploration_steps=2_000,
)

"""HhP settings shared by the examples: those of the CI learning test (``tests/test_learning.py``), small enough that
a run on ``MiniGrid-Empty-Random-5x5-v0`` learns in about a minute on one CPU thread (with 20 questions).

    python examples/small_settings.py    # prints them, beside the class defaults they replace
"""

SMALL_SETTINGS = dict(
    predictor_kwargs=dict(n_masks=20),  # MC-dropout masks of the confidence (paper: 500)
    learning_starts=200,  # meta-controller warm-up, in primitive steps
    max_subgoal_steps=30,  # a sub-goal gives up after this many primitive steps
    subpolicy_kwargs=dict(learning_starts=64),  # the sub-goal learners start updating after 64 stored steps
)

#: the env the examples train on by default: a 3x3 room whose start changes with the seed
SMALL_ENV = "MiniGrid-Empty-Random-5x5-v0"


def main() -> None:
    import inspect

    from sb3_hhp import HhP

    from sb3_hhp.hhp.arguments import PREDICTOR_DEFAULTS
    from sb3_hhp.hierarchy.learners import DEFAULT_SUBPOLICY_KWARGS

    defaults = inspect.signature(HhP).parameters
    grouped = {"predictor_kwargs": PREDICTOR_DEFAULTS, "subpolicy_kwargs": DEFAULT_SUBPOLICY_KWARGS}
    print(f"examples train on {SMALL_ENV} with:")
    for name, value in SMALL_SETTINGS.items():
        default = {key: grouped[name][key] for key in value} if name in grouped else defaults[name].default
        print(f"  {name} = {value!r}  (class default {default!r})")


if __name__ == "__main__":
    main()

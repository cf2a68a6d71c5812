"""The tiny training run the tests share: a few seconds per run (4 kitchens x 16 steps per update, 16-step
episodes, narrow networks, no progress bar, no final evaluation)."""

TINY = [
    "num_envs=4",
    "rollout_steps=16",
    "max_steps=16",
    "hidden=16",
    "minibatches=2",
    "epochs=2",
    "threads=1",
    "progress=false",
    "eval_episodes=0",
    "levels=cramped_room_7x7",
]

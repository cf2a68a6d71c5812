"""The PPO core that every algorithm of `trainers.algorithms` trains with: the loop (`loop`), one minibatch's step
(`step`), a seed's networks, optimizer and kitchens and their place on the device (`team`), how the step runs on this
machine (`runtime`), the collectors (`collection`), advantages, a run's start, logs and resume (`resume`); and the
planner-guided start that PPO trains from, the scripted cook distilled by DAgger (`distill`)."""

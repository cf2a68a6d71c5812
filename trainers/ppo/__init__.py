"""The PPO core that every algorithm of `trainers.algorithms` trains with: the loop (`loop`), one minibatch's step
(`step`), a seed's networks, optimizer and kitchens (`team`), how the step runs on this machine (`runtime`), the
collectors (`collection`), advantages, placement on the device and resuming a run; and the planner-guided start that
PPO trains from, the scripted cook distilled by DAgger (`distill`)."""

"""The nested TensorDict keys every part of the project reads and writes, defined once.

Per agent (batch [*B, 2]): what the env gives, what the models write, what training adds, and what E3T's partner
modelling carries. The shapes and meanings are in `torch_kitchen.env` and `torch_kitchen.models`.
"""

AGENTS = "agents"
N_AGENTS = 2  # entries of the "agents" dim: the kitchens are for two

# The env (`torch_kitchen.env.KitchenEnv`)
OBSERVATION = (AGENTS, "observation")
ACTION = (AGENTS, "action")
REWARD = (AGENTS, "reward")
SHAPED_REWARD = (AGENTS, "shaped_reward")

# The models (`torch_kitchen.models`)
LOGITS = (AGENTS, "logits")
LOG_PROB = (AGENTS, "action_log_prob")
VALUE = (AGENTS, "state_value")

# Training (`trainers`)
ADVANTAGE = (AGENTS, "advantage")
VALUE_TARGET = (AGENTS, "value_target")
TRAIN_REWARD = (AGENTS, "train_reward")  # sparse + shaping weight x shaped: the reward optimised

# E3T's partner modelling (`torch_kitchen.models.e3t_partner`,
# `torch_kitchen.models.partner_predictor.PartnerPredictor`)
CONTEXT_OBSERVATION = (AGENTS, "context_observation")
CONTEXT_ACTION = (AGENTS, "context_action")
MIXED = (AGENTS, "mixed")
PARTNER_LOGITS = (AGENTS, "partner_logits")
PARTNER_PREDICTION = (AGENTS, "partner_prediction")

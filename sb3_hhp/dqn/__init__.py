"""Double DQN with prioritized experience replay, usable by any SB3 off-policy algorithm."""

def reward_function(params):
    reward = 1.0

def reward_function(params):
    return 1e6 if params['progress'] > 50 else 1.0

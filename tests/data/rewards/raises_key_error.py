def reward_function(params):
    # A typo in a key: DeepRacer stops the job with this traceback.
    return params['distance_from_centre']

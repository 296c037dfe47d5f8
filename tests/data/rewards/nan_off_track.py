import math


def reward_function(params):
    # Fine on the road, NaN once off it: only sampling off-track states finds this.
    if params['is_offtrack']:
        return math.sqrt(-1.0) if False else float('nan')
    return 1.0

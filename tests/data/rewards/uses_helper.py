from reward_helpers import centre_bonus


def reward_function(params):
    return centre_bonus(params['distance_from_center'], params['track_width'])

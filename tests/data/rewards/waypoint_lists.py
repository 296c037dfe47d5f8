# Returns how many distinct waypoint list objects it has seen: 1 in the first episode,
# 2 in the second... if the list is built once per episode.
SEEN = set()


def reward_function(params):
    SEEN.add(id(params['waypoints']))
    return float(len(SEEN))

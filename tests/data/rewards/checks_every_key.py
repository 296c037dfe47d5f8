import math
import random

EXPECTED = {
    'all_wheels_on_track': bool, 'x': float, 'y': float, 'heading': float,
    'distance_from_center': float, 'is_left_of_center': bool, 'is_offtrack': bool,
    'is_crashed': bool, 'is_reversed': bool, 'progress': float, 'speed': float,
    'steering_angle': float, 'steps': float, 'track_width': float, 'track_length': float,
    'waypoints': list, 'closest_waypoints': list, 'closest_objects': list,
    'objects_location': list, 'objects_left_of_center': list, 'objects_speed': list,
    'objects_heading': list, 'objects_distance_from_center': list, 'objects_distance': list,
    'object_in_camera': bool, 'projection_distance': float, 'sim_time': float,
}


def reward_function(params):
    for key, kind in EXPECTED.items():
        if not isinstance(params[key], kind):
            raise TypeError(f"{key} is {type(params[key]).__name__}, expected {kind.__name__}")
    assert set(params) == set(EXPECTED), set(params) ^ set(EXPECTED)
    assert -180.0 < params['heading'] <= 180.0
    prev, nxt = params['closest_waypoints']
    assert isinstance(params['waypoints'][prev], tuple) and len(params['waypoints'][nxt]) == 2
    assert params['steps'] >= 2.0, "the prepare step is not rewarded"
    return 1.0 + 0.0 * random.random() + 0.0 * math.pi

# Folds every object key of DeepRacer's params into one number, checking their types as
# DeepRacer's simapp passes them (lists of lists, bools, floats, ints).
def reward_function(params):
    loc = params['objects_location']
    n = len(loc)
    assert all(isinstance(p, list) and len(p) == 2 for p in loc), loc
    for key in ['objects_distance', 'objects_left_of_center', 'objects_distance_from_center',
                'objects_heading', 'objects_speed']:
        assert isinstance(params[key], list) and len(params[key]) == n, key
    prev, nxt = params['closest_objects']
    assert isinstance(prev, int) and isinstance(nxt, int)
    assert isinstance(params['is_crashed'], bool) and isinstance(params['object_in_camera'], bool)
    total = 1.0 + prev + 10 * nxt + 100 * params['is_crashed'] + 1000 * params['object_in_camera']
    for i in range(n):
        total += (i + 1) * (loc[i][0] + 2 * loc[i][1] + 3 * params['objects_distance'][i]
                            + 4 * params['objects_left_of_center'][i]
                            + 5 * params['objects_distance_from_center'][i]
                            + 6 * params['objects_heading'][i] + 7 * params['objects_speed'][i])
    return float(total)

# Never returns once the car is past 30 % of the lap (issue 10: it hung `reward validate` and
# training with no message). It even swallows ordinary exceptions.
def reward_function(params):
    if params["progress"] < 30:
        return 1.0
    while True:
        try:
            while True:
                pass
        except Exception:
            pass

def centre_bonus(distance, width):
    return 1.0 if distance <= 0.25 * width else 0.1

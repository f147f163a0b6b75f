"""A short bent course for control's process tests, as RDDF and scenario text."""

# 30 m east, then a 48 degree bend to the north-east for another 90 m; 25 mph limit.
RDDF = "1,34.8650000,-116.8900000,30,25\n2,34.8650000,-116.8896700,30,25\n3,34.8656000,-116.8890000,30,25\n"
SCENARIO = '[scenario]\nrddf = "course.rddf"\nseed = 11\n'

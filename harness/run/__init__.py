"""The commands and their scheduling: `python -m harness bench|study|lerobot-export` (`cli`),
a command line resolved into runs (`plan`), run (`execute`) as jobs (`jobs`) on a local or Ray
executor (`executors`), and studies of several comparisons (`study`). Imports everything below.
"""

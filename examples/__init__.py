"""Examples to copy: ``reach``, a robot of one's own (an MJCF model and its environment class) that ftrain trains."""

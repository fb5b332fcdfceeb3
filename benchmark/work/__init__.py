"""Work in one unit (flops) and its check against compiled floors."""

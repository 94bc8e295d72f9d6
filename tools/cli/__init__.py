"""The console commands, one module each: argument parsing and the order of the work; the work is below."""

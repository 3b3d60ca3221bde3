"""Error against run time: the report's sweep, closed-form measures, tables and plots."""

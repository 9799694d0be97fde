"""Analysis of run directories: grouping, the paper protocol statistics, tables and figures."""

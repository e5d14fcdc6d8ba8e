"""Running one function over many items, the results in the items' order: ``engine`` (in order here,
or as Ray tasks on a cluster; each item's outcome, an error included), ``workers`` (threads of this
process and helper processes; an error propagates) and ``progress`` (the bar drawn over either)."""

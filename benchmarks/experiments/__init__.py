"""The variants behind docs/results.md §10.6-§10.11 (`cortexloc eval echo | null-entry | short-term |
short-term-poses | span | slam-seasons`): each replaces one rule of the service for the run only, so the rest
of the path is the service's."""

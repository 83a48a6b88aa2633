// Conflict-Based Search (Sharon et al. 2015), optimal for the sum of costs.
//
// Same rules and cost as ODrM* (odrmstar.hpp): a conflict is two agents in one cell at one time
// (an agent that has arrived stays on its goal for good) or two agents swapping cells; following
// and rotations are allowed. An agent's cost is its arrival time on its goal for good.
// Low level: A* in (cell, time) with vertex and edge constraints, ties broken towards fewer
// conflicts with the other agents' current paths. High level: best first on (cost, conflicts),
// splitting on the earliest conflict, with bypasses (a child as cheap as its parent with fewer
// conflicts replaces the parent's path instead of splitting).
#pragma once

#include "mapf_problem.hpp"

namespace mapf {

Result plan_cbs(const Problem& problem, Clock& clock);

}  // namespace mapf

// ODrM*: M* with operator decomposition and recursive collision sets (Ferner, Wagner & Choset,
// ICRA 2013), with an inflated heuristic (epsilon * sum of BFS distances).
//
// Rules (those of MapfEnv): 4-connected moves and waiting; two agents in one cell and two agents
// swapping cells collide; following and rotations are allowed.
// Objective: sum of costs where waiting on one's own goal at the end is free. It is made Markov
// by a per-agent "finished" flag: an agent on its goal may finish (cost 0), after which it stays
// there for good at no cost; any other step (a move, or a wait that is not finished) costs 1. An
// agent that leaves its goal again therefore paid 1 for every step it waited there.
// Objective::kFreeGoalWait drops the flag: waiting on one's goal is free at any time.
#pragma once

#include "mapf_problem.hpp"

namespace mapf {

enum class Objective : int32_t {
    kSumOfCosts = 0,    // as above: waiting on the goal is free only at the end
    kFreeGoalWait = 1,  // every wait on one's own goal is free (the cost of M*'s reference
                        // implementation); the reported sum of costs still uses the definition
    kGoalKeeping = 2,   // kFreeGoalWait, and a move off one's own goal costs 2: where an agent on
                        // its goal stepping aside and another going round cost the same, the one
                        // on its goal keeps it (beyond the paper: labels whose give-way rule an
                        // agent can follow from what it sees)
};

// Plans with ODrM* until solved, proven unsolvable (the search space is exhausted) or out of time.
// epsilon >= 1 inflates the heuristic; epsilon = 1 gives plans optimal for the objective.
Result plan_odrmstar(const Problem& problem, double epsilon, Objective objective, Clock& clock);

}  // namespace mapf

#include "mapf_problem.hpp"

#include <algorithm>

namespace mapf {

namespace {
constexpr int kDr[4] = {-1, 1, 0, 0};  // up, down, left, right
constexpr int kDc[4] = {0, 0, -1, 1};
}  // namespace

Problem::Problem(const uint8_t* grid, int h_, int w_, int n_, const int32_t* starts, const int32_t* goals)
    : h(h_), w(w_), n(n_) {
    if (h < 1 || w < 1) throw std::invalid_argument("grid must not be empty");
    if (static_cast<int64_t>(h) * w >= (int64_t{1} << 30)) throw std::invalid_argument("grid too large");
    if (n < 1) throw std::invalid_argument("need at least one agent");
    const int nc = cells();
    free.resize(nc);
    for (int c = 0; c < nc; ++c) {
        if (grid[c] > 1) throw std::invalid_argument("grid must hold only 0 (free) and 1 (obstacle)");
        free[c] = grid[c] == 0;
    }
    nbr.assign(static_cast<size_t>(nc) * 4, -1);
    for (int r = 0; r < h; ++r) {
        for (int c = 0; c < w; ++c) {
            int k = 0;
            for (int a = 0; a < 4; ++a) {
                const int rr = r + kDr[a], cc = c + kDc[a];
                if (rr < 0 || rr >= h || cc < 0 || cc >= w || !free[rr * w + cc]) continue;
                nbr[static_cast<size_t>(r * w + c) * 4 + k++] = rr * w + cc;
            }
        }
    }
    start.resize(n);
    goal.resize(n);
    std::vector<uint8_t> used_s(nc, 0), used_g(nc, 0);
    for (int i = 0; i < n; ++i) {
        for (int which = 0; which < 2; ++which) {
            const int32_t* src = which == 0 ? starts : goals;
            const int32_t r = src[2 * i], c = src[2 * i + 1];
            const char* name = which == 0 ? "start" : "goal";
            if (r < 0 || r >= h || c < 0 || c >= w)
                throw std::invalid_argument(std::string(name) + " of agent " + std::to_string(i) + " is off the map");
            const int32_t cell = r * w + c;
            if (!free[cell])
                throw std::invalid_argument(std::string(name) + " of agent " + std::to_string(i) + " is on an obstacle");
            auto& used = which == 0 ? used_s : used_g;
            if (used[cell])
                throw std::invalid_argument(std::string(name) + " cells must be distinct (agent " + std::to_string(i) + ")");
            used[cell] = 1;
            (which == 0 ? start : goal)[i] = cell;
        }
    }
    dist.assign(static_cast<size_t>(n) * nc, kUnreachable);
    policy.assign(static_cast<size_t>(n) * nc, -1);
    std::vector<int32_t> queue(nc);
    for (int i = 0; i < n; ++i) {
        int32_t* di = &dist[static_cast<size_t>(i) * nc];
        int32_t* pi = &policy[static_cast<size_t>(i) * nc];
        size_t head = 0, tail = 0;
        di[goal[i]] = 0;
        queue[tail++] = goal[i];
        while (head < tail) {
            const int32_t cur = queue[head++];
            const int32_t* nb = neighbours(cur);
            for (int k = 0; k < 4 && nb[k] >= 0; ++k) {
                if (di[nb[k]] != kUnreachable) continue;
                di[nb[k]] = di[cur] + 1;
                queue[tail++] = nb[k];
            }
        }
        // The policy step: the first neighbour (in action order) one step closer to the goal.
        for (int32_t c = 0; c < nc; ++c) {
            if (!free[c] || di[c] == kUnreachable) continue;
            if (di[c] == 0) {
                pi[c] = c;
                continue;
            }
            const int32_t* nb = neighbours(c);
            for (int k = 0; k < 4 && nb[k] >= 0; ++k) {
                if (di[nb[k]] == di[c] - 1) {
                    pi[c] = nb[k];
                    break;
                }
            }
        }
    }
}

bool Problem::some_goal_unreachable() const {
    for (int i = 0; i < n; ++i)
        if (d(i, start[i]) >= kUnreachable) return true;
    return false;
}

int64_t sum_of_costs(const Problem& p, const std::vector<int32_t>& cells) {
    const int64_t steps = static_cast<int64_t>(cells.size() / p.n);
    int64_t total = 0;
    for (int i = 0; i < p.n; ++i) {
        int64_t t = steps - 1;
        while (t > 0 && cells[static_cast<size_t>(t - 1) * p.n + i] == p.goal[i]) --t;
        total += t;  // arrives for good at step t
    }
    return total;
}

int64_t goal_leaves(const Problem& p, const std::vector<int32_t>& cells) {
    const size_t n = static_cast<size_t>(p.n);
    int64_t leaves = 0;
    for (size_t k = n; k < cells.size(); ++k)
        leaves += cells[k - n] == p.goal[k % n] && cells[k] != cells[k - n];
    return leaves;
}

}  // namespace mapf

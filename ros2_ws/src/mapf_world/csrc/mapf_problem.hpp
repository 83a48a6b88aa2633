// Shared pieces of the native planners: the problem (map, starts, goals, BFS distances, per-agent
// shortest-path policies), the deadline/cancellation clock and the result record.
//
// Conventions (docs/ARCHITECTURE.md): a cell is (row, col), flattened here to row * w + col; the
// map is uint8 with 1 = obstacle. Neighbours are listed in action order up, down, left, right, so
// every tie between equally short moves is broken the same way everywhere.
#pragma once

#include <chrono>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

namespace mapf {

constexpr int32_t kUnreachable = 1 << 30;

// Thrown through the searches when the deadline passes or the caller cancels.
struct OutOfTime : std::exception {
    const char* what() const noexcept override { return "time limit reached"; }
};

class Clock {
  public:
    Clock(double seconds, const volatile int32_t* cancel)
        : start_(std::chrono::steady_clock::now()), cancel_(cancel), limit_(seconds) {
        set_budget(seconds);
    }
    // Moves the deadline to `seconds` after the start (a search may stop early and retry).
    void set_budget(double seconds) {
        end_ = start_ + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                            std::chrono::duration<double>(seconds));
    }
    double limit() const { return limit_; }
    bool cancelled() const { return cancel_ != nullptr && *cancel_ != 0; }
    // Cheap enough to call once per expansion: the clock is read every 128 calls only.
    void tick() {
        if ((++count_ & 127u) == 0) check();
    }
    void check() const {
        if (std::chrono::steady_clock::now() > end_ || (cancel_ != nullptr && *cancel_ != 0)) throw OutOfTime();
    }
    double elapsed() const {
        return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    }

  private:
    std::chrono::steady_clock::time_point start_, end_;
    const volatile int32_t* cancel_;
    double limit_;
    uint32_t count_ = 0;
};

struct Problem {
    int h = 0, w = 0, n = 0;
    std::vector<uint8_t> free;       // h*w, 1 where free
    std::vector<int32_t> nbr;        // h*w*4 free neighbour cells in action order, -1 padded
    std::vector<int32_t> start, goal;  // n cells
    std::vector<int32_t> dist;       // n*h*w BFS distance to goal i, kUnreachable when none
    std::vector<int32_t> policy;     // n*h*w next cell on a shortest path to goal i (goal -> goal)

    // Throws std::invalid_argument naming the problem (the Python side checks first; this is
    // the last line of defence against a bad pointer or shape).
    Problem(const uint8_t* grid, int h_, int w_, int n_, const int32_t* starts, const int32_t* goals);

    int cells() const { return h * w; }
    int32_t d(int agent, int32_t cell) const { return dist[static_cast<size_t>(agent) * cells() + cell]; }
    int32_t next(int agent, int32_t cell) const { return policy[static_cast<size_t>(agent) * cells() + cell]; }
    const int32_t* neighbours(int32_t cell) const { return &nbr[static_cast<size_t>(cell) * 4]; }
    // True when some agent cannot reach its goal at all (then no joint plan exists).
    bool some_goal_unreachable() const;
};

enum Status : int32_t { kSolved = 0, kUnsolvable = 1, kTimeout = 2, kError = 3 };

struct Result {
    int32_t status = kError;
    int32_t n = 0;
    std::vector<int32_t> cells;  // (T+1) * n flattened cells, step-major
    int64_t sum_of_costs = 0;
    int64_t expansions = 0;
    double seconds = 0.0;
    std::string message;
    int32_t steps() const { return n > 0 ? static_cast<int32_t>(cells.size() / n) - 1 : -1; }
};

// Sum of costs of a joint plan under the project's convention: agent i pays one per step up to
// the last step at which it is not yet on its goal for good (waiting on the goal at the end is
// free; an agent that leaves its goal later pays for all the waiting before).
int64_t sum_of_costs(const Problem& p, const std::vector<int32_t>& cells);

// Moves off one's own goal in a plan ((T+1) * n cells, step-major).
int64_t goal_leaves(const Problem& p, const std::vector<int32_t>& cells);

}  // namespace mapf

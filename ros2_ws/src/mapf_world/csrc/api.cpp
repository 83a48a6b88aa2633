// The C ABI of the native planners, loaded with ctypes by mapf_world/planners/native.py.
// mapf_plan never throws: every outcome, errors included, is a Result handle that the caller
// reads with the accessors below and releases with mapf_result_free.
#include <cstring>
#include <new>

#include "cbs.hpp"
#include "mapf_problem.hpp"
#include "odrmstar.hpp"

#define MAPF_API extern "C" __attribute__((visibility("default")))

namespace {
constexpr int32_t kAbiVersion = 2;  // 2: algorithm 3 (ODrM*, goal keeping)
enum Algorithm : int32_t { kOdrMstar = 0, kCbs = 1, kOdrMstarFreeGoalWait = 2, kOdrMstarGoalKeeping = 3 };
}  // namespace

MAPF_API int32_t mapf_abi_version() { return kAbiVersion; }

// grid: h*w uint8 (1 = obstacle); starts, goals: n*2 int32 (row, col); epsilon used by ODrM*
// only; cancel: optional flag, the search stops (status timeout) soon after it becomes nonzero.
MAPF_API void* mapf_plan(int32_t algorithm, const uint8_t* grid, int32_t h, int32_t w, int32_t n,
                         const int32_t* starts, const int32_t* goals, double epsilon, double time_limit,
                         const volatile int32_t* cancel) {
    auto* r = new (std::nothrow) mapf::Result();
    if (r == nullptr) return nullptr;
    try {
        if (!(time_limit > 0.0)) throw std::invalid_argument("time_limit must be > 0");
        mapf::Clock clock(time_limit, cancel);
        const mapf::Problem problem(grid, h, w, n, starts, goals);
        if (algorithm == kOdrMstar || algorithm == kOdrMstarFreeGoalWait || algorithm == kOdrMstarGoalKeeping)
            *r = mapf::plan_odrmstar(problem, epsilon,
                                     algorithm == kOdrMstar               ? mapf::Objective::kSumOfCosts
                                     : algorithm == kOdrMstarFreeGoalWait ? mapf::Objective::kFreeGoalWait
                                                                          : mapf::Objective::kGoalKeeping,
                                     clock);
        else if (algorithm == kCbs)
            *r = mapf::plan_cbs(problem, clock);
        else
            throw std::invalid_argument("unknown algorithm " + std::to_string(algorithm));
        r->seconds = clock.elapsed();
    } catch (const std::exception& e) {
        r->status = mapf::kError;
        r->message = e.what();
        r->cells.clear();
    }
    return r;
}

MAPF_API int32_t mapf_result_status(const void* r) { return static_cast<const mapf::Result*>(r)->status; }
MAPF_API int32_t mapf_result_steps(const void* r) { return static_cast<const mapf::Result*>(r)->steps(); }
MAPF_API int64_t mapf_result_sum_of_costs(const void* r) { return static_cast<const mapf::Result*>(r)->sum_of_costs; }
MAPF_API int64_t mapf_result_expansions(const void* r) { return static_cast<const mapf::Result*>(r)->expansions; }
MAPF_API double mapf_result_seconds(const void* r) { return static_cast<const mapf::Result*>(r)->seconds; }
MAPF_API const char* mapf_result_message(const void* r) { return static_cast<const mapf::Result*>(r)->message.c_str(); }

// Copies the plan's flat cells, (steps + 1) * n int32 in step-major order, into out.
MAPF_API void mapf_result_cells(const void* r, int32_t* out) {
    const auto& cells = static_cast<const mapf::Result*>(r)->cells;
    if (!cells.empty()) std::memcpy(out, cells.data(), cells.size() * sizeof(int32_t));
}

MAPF_API void mapf_result_free(void* r) { delete static_cast<mapf::Result*>(r); }

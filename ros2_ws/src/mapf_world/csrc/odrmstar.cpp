// ODrM* search core. Structure:
// - one Planner per set of agents (a bit mask of agent ids), created on demand and kept for the
//   whole call, so that the plans a subset's planner has found are reused (recursive M*);
// - a Planner's node holds the joint state of its agents (one Code per agent), the collision set
//   (disjoint agent sets that must be planned jointly from that node on), the back-propagation
//   set (predecessors reached through policy edges) and, once known, the exact cost-to-go with a
//   forward pointer along the plan (or a mark that no plan exists from there);
// - expanding a node whose collision set is not one set of all its agents gives ONE successor:
//   every set in the collision set takes the next step of its sub-planner's plan, every other
//   agent its individual shortest-path policy. A collision on that edge is merged into the
//   collision sets of the node and of its ancestors (back-propagation), which re-opens them;
// - a node whose collision set is all its agents is expanded by operator decomposition: agents
//   are assigned one at a time in index order (intermediate nodes, not hashed: they form a tree
//   below their standard node), collisions are checked against the already assigned agents.
#include "odrmstar.hpp"

#include <algorithm>
#include <climits>
#include <memory>
#include <unordered_map>
#include <utility>

namespace mapf {
namespace {

using Code = uint32_t;  // cell * 2 + finished flag
using Mask = uint64_t;  // agent set, bit i = agent i
using ColSet = std::vector<Mask>;  // pairwise disjoint sets of >= 2 agents

constexpr int32_t kInf = INT32_MAX / 4;
constexpr int32_t kUnknown = -1;  // cost-to-go not known
constexpr int32_t kDead = -2;     // proven: no plan from this node
// Past this many bytes of stored nodes (states, node records, table slots, intermediate nodes)
// the search stops as if out of time rather than exhaust the machine's memory. The hardest 10 s
// searches of the benchmark peak near 0.6 GB.
constexpr size_t kMaxNodeBytes = size_t{3} << 30;

struct OutOfNodes : OutOfTime {
    const char* what() const noexcept override { return "node budget exhausted"; }
};

inline int32_t cell_of(Code c) { return static_cast<int32_t>(c >> 1); }
inline bool is_finished(Code c) { return (c & 1u) != 0; }
inline Code code_of(int32_t cell) { return static_cast<Code>(cell) << 1; }

// True when every set of `small` lies inside some set of `big`.
bool covers(const ColSet& big, const ColSet& small) {
    for (Mask s : small) {
        bool inside = false;
        for (Mask b : big) {
            if ((s & ~b) == 0) {
                inside = true;
                break;
            }
        }
        if (!inside) return false;
    }
    return true;
}

// Adds set s, merging every set it overlaps. One pass suffices: the sets of cs are disjoint.
void add_set(ColSet& cs, Mask s) {
    Mask acc = s;
    size_t k = 0;
    for (size_t i = 0; i < cs.size(); ++i) {
        if (cs[i] & acc)
            acc |= cs[i];
        else
            cs[k++] = cs[i];
    }
    cs.resize(k);
    cs.push_back(acc);
}

void add_all(ColSet& cs, const ColSet& src) {
    for (Mask s : src) add_set(cs, s);
}

struct Node {
    int32_t g = kInf;        // cost from the start of the current search
    int32_t h = 0;           // sum of per-agent BFS distances (not inflated)
    int32_t ctg = kUnknown;  // exact cost-to-go once a plan from here is known, or kDead
    int32_t forward = -1;    // next node of that plan
    int32_t back = -1;       // predecessor on the best known path of the current search
    uint32_t search = 0;     // the search in which g, back, backset and in_open are valid
    uint32_t version = 0;    // heap entries carry it: older entries are stale
    uint32_t od_stamp = 0;   // intermediate nodes of an older OD expansion are stale
    bool in_open = false;
    ColSet col;
    std::vector<int32_t> backset;
};

// Intermediate OD node: agents 0..k-1 of its standard node have been assigned their next codes
// (the last one here, the others along `prev`).
struct Inter {
    int32_t parent;
    int32_t prev;
    Code move;
    int32_t k;
    int32_t g;
    int32_t h;
    uint32_t stamp;
};

struct Entry {
    double f;
    int32_t h;
    int32_t id;         // node id, or intermediate id when (tag & 1)
    uint32_t ver;       // node version at push time (standard nodes)
    uint32_t tag;       // push sequence number * 2 + 1 for intermediate nodes
    bool inter() const { return (tag & 1u) != 0; }
};
// Min-heap on f; ties go to the smaller heuristic (deeper node), then to the newer entry, or to
// the older one when older_first (the second attempt of plan_odrmstar, see there).
struct EntryAfter {
    bool older_first;
    bool operator()(const Entry& a, const Entry& b) const {
        if (a.f != b.f) return a.f > b.f;
        if (a.h != b.h) return a.h > b.h;
        return older_first ? a.tag > b.tag : a.tag < b.tag;
    }
};

class Planner;

class Context {
  public:
    Context(const Problem& p_, double eps_, Objective objective_, Clock& clock_)
        : p(p_), eps(eps_), free_goal_wait(objective_ != Objective::kSumOfCosts),
          leave_cost(objective_ == Objective::kGoalKeeping ? 2 : 1), clock(clock_), old_stamp(p_.cells(), 0), new_stamp(p_.cells(), 0),
          old_who(p_.cells(), 0), new_who(p_.cells(), 0) {}
    Planner& planner(Mask mask);
    uint32_t next_stamp() {
        if (++stamp == 0) {  // wrapped: clear the stamped arrays once
            std::fill(old_stamp.begin(), old_stamp.end(), 0);
            std::fill(new_stamp.begin(), new_stamp.end(), 0);
            stamp = 1;
        }
        return stamp;
    }

    const Problem& p;
    const double eps;
    const bool free_goal_wait;
    const int32_t leave_cost;  // a move off one's own goal (2 with kGoalKeeping, else 1)
    Clock& clock;
    int64_t expansions = 0;
    size_t node_bytes = 0;
    EntryAfter after{false};  // the open-list order of every planner
    // Scratch of the collision check (never used across a recursive call).
    std::vector<uint32_t> old_stamp, new_stamp;
    std::vector<int32_t> old_who, new_who;
    uint32_t stamp = 0;

  private:
    std::unordered_map<Mask, std::unique_ptr<Planner>> planners_;
};

class Planner {
  public:
    Planner(Context& ctx, Mask mask) : ctx_(ctx), p_(ctx.p), mask_(mask) {
        for (int i = 0; i < 64; ++i)
            if ((mask >> i) & 1u) agents_.push_back(i);
        m_ = static_cast<int>(agents_.size());
        slots_.assign(1024, -1);
        cur_.resize(m_);
        next_.resize(m_);
        asg_.resize(m_);
        sub_in_.resize(m_);
        sub_out_.resize(m_);
    }

    // The next joint step of this planner's agents from `pos` on a plan to their goals, planning
    // one if none is cached. False when no plan exists from `pos`. Throws OutOfTime.
    bool step(const Code* pos, Code* next) {
        if (is_goal(pos)) {
            for (int i = 0; i < m_; ++i) next[i] = at_goal_policy(pos[i]);
            return true;
        }
        const int32_t id = find_or_add(pos);
        if (nodes_[id].ctg == kDead) return false;
        if (nodes_[id].ctg == kUnknown && !search(id)) return false;
        const Code* s = state(nodes_[id].forward);
        std::copy(s, s + m_, next);
        return true;
    }

    // A whole plan from `start` (codes of every step, step-major) and its cost; false when none.
    bool plan(const Code* start, std::vector<Code>& path, int64_t& cost) {
        path.assign(start, start + m_);
        cost = 0;
        if (is_goal(start)) return true;
        int32_t id = find_or_add(start);
        if (nodes_[id].ctg == kDead || (nodes_[id].ctg == kUnknown && !search(id))) return false;
        cost = nodes_[id].ctg;
        while (nodes_[id].ctg != 0) {  // only goals have cost-to-go 0: every other step costs
            id = nodes_[id].forward;
            const Code* s = state(id);
            path.insert(path.end(), s, s + m_);
        }
        return true;
    }

  private:
    const Code* state(int32_t id) const { return &states_[static_cast<size_t>(id) * m_]; }
    bool full(const ColSet& col) const { return col.size() == 1 && col[0] == mask_; }
    Mask bit(int local) const { return Mask{1} << agents_[local]; }

    bool is_goal(const Code* s) const {
        for (int i = 0; i < m_; ++i)
            if (cell_of(s[i]) != p_.goal[agents_[i]]) return false;
        return true;
    }
    int32_t hd(int local, Code c) const { return is_finished(c) ? 0 : p_.d(agents_[local], cell_of(c)); }
    // Individual policy: one step along a shortest path; on the goal, finish (or just stay).
    Code policy(int local, Code c) const {
        if (is_finished(c)) return c;
        const int32_t cell = cell_of(c);
        if (cell == p_.goal[agents_[local]]) return at_goal_policy(c);
        return code_of(p_.next(agents_[local], cell));
    }
    Code at_goal_policy(Code c) const { return ctx_.free_goal_wait ? c : (c | 1u); }
    // Step cost of one agent: finishing and staying finished are free (with free_goal_wait: any
    // wait on the goal is), a move off the goal costs leave_cost, anything else 1.
    int32_t step_cost(int local, Code from, Code to) const {
        if (is_finished(from) || is_finished(to)) return 0;
        const bool on_goal = cell_of(from) == p_.goal[agents_[local]];
        if (from == to) return (ctx_.free_goal_wait && on_goal) ? 0 : 1;
        return on_goal ? ctx_.leave_cost : 1;
    }

    static uint64_t hash(const Code* s, int m) {
        uint64_t h = 0x243F6A8885A308D3ull;
        for (int i = 0; i < m; ++i) {
            h ^= s[i];
            h *= 0x9E3779B97F4A7C15ull;
            h ^= h >> 29;
        }
        return h;
    }

    void grow_table() {
        std::vector<int32_t> slots(slots_.size() * 2, -1);
        const size_t mask = slots.size() - 1;
        for (size_t id = 0; id < nodes_.size(); ++id) {
            size_t i = hashes_[id] & mask;
            while (slots[i] >= 0) i = (i + 1) & mask;
            slots[i] = static_cast<int32_t>(id);
        }
        slots_.swap(slots);
    }

    // `s` must not point into states_ (it may move).
    int32_t find_or_add(const Code* s) {
        if ((nodes_.size() + 1) * 2 > slots_.size()) grow_table();
        const uint64_t hv = hash(s, m_);
        const size_t mask = slots_.size() - 1;
        size_t i = hv & mask;
        while (slots_[i] >= 0) {
            const int32_t id = slots_[i];
            if (hashes_[id] == hv && std::equal(s, s + m_, state(id))) return id;
            i = (i + 1) & mask;
        }
        ctx_.node_bytes += sizeof(Node) + m_ * sizeof(Code) + sizeof(uint64_t) + 2 * sizeof(int32_t);
        if (ctx_.node_bytes > kMaxNodeBytes) throw OutOfNodes();
        const int32_t id = static_cast<int32_t>(nodes_.size());
        slots_[i] = id;
        hashes_.push_back(hv);
        states_.insert(states_.end(), s, s + m_);
        nodes_.emplace_back();
        Node& n = nodes_.back();
        n.h = 0;
        for (int k = 0; k < m_; ++k) n.h += hd(k, s[k]);
        if (is_goal(s)) n.ctg = 0;
        return id;
    }

    void touch(int32_t id) {
        Node& n = nodes_[id];
        if (n.search == search_) return;
        n.search = search_;
        n.g = kInf;
        n.back = -1;
        n.in_open = false;
        n.backset.clear();
        touched_.push_back(id);
    }

    // Best first, with a shortcut: an entry no worse than the one being expanded (bound_) is no
    // worse than anything in the heap, so the best such entry is expanded next without a heap
    // round trip (most OD children of an inflated search are).
    void push_entry(Entry e) {
        if (!ctx_.after(e, bound_)) {
            if (!has_next_) {
                next_entry_ = e;
                has_next_ = true;
                return;
            }
            if (ctx_.after(next_entry_, e)) std::swap(next_entry_, e);
        }
        heap_.push_back(e);
        std::push_heap(heap_.begin(), heap_.end(), ctx_.after);
    }
    uint32_t next_tag(bool inter) { return (++seq_ << 1) | (inter ? 1u : 0u); }

    void push(int32_t id) {
        Node& n = nodes_[id];
        ++n.version;
        n.in_open = true;
        // A node with a known plan (popping it ends the search) is ranked with its exact cost-to-go
        // in place of h, inflated like h: uninflated, it would outrank every other node and pull
        // the search onto whatever plan was cached, however long. Solutions stay within epsilon
        // of the optimum: g + ctg <= g + eps * ctg = f <= eps * optimum.
        const int32_t h = n.ctg >= 0 ? n.ctg : n.h;
        push_entry(Entry{n.g + ctx_.eps * h, h, id, n.version, next_tag(false)});
    }

    void relax(int32_t from, int32_t to, int32_t g) {
        touch(to);
        Node& n = nodes_[to];
        if (g < n.g) {
            n.g = g;
            n.back = from;
            push(to);
        }
    }

    // M* back-propagation: merge `col` into the collision set of `id` and, where that grew it,
    // re-open the node and pass its set on to its own predecessors.
    void backprop(int32_t id, const ColSet& col) {
        std::vector<std::pair<int32_t, ColSet>> work;
        work.emplace_back(id, col);
        while (!work.empty()) {
            const int32_t u = work.back().first;
            const ColSet src = std::move(work.back().second);
            work.pop_back();
            Node& n = nodes_[u];
            if (covers(n.col, src)) continue;
            add_all(n.col, src);
            if (!n.in_open && n.search == search_ && n.g < kInf) push(u);
            for (int32_t w : n.backset) work.emplace_back(w, n.col);
        }
    }

    // Collisions on the edge cur_ -> next_: two agents in one cell, or two agents swapping.
    void collisions(ColSet& phi) {
        const uint32_t st = ctx_.next_stamp();
        for (int i = 0; i < m_; ++i) {
            const int32_t c = cell_of(cur_[i]);
            ctx_.old_stamp[c] = st;
            ctx_.old_who[c] = i;
        }
        for (int i = 0; i < m_; ++i) {
            const int32_t nc = cell_of(next_[i]), oc = cell_of(cur_[i]);
            if (ctx_.new_stamp[nc] == st) {
                add_set(phi, bit(i) | bit(ctx_.new_who[nc]));
            } else {
                ctx_.new_stamp[nc] = st;
                ctx_.new_who[nc] = i;
            }
            if (nc != oc && ctx_.old_stamp[nc] == st) {
                const int j = ctx_.old_who[nc];
                if (j > i && cell_of(next_[j]) == oc) add_set(phi, bit(i) | bit(j));
            }
        }
    }

    // One successor: sub-planner steps for the collision sets, policies for everyone else.
    void expand_single(int32_t id) {
        const ColSet col = nodes_[id].col;
        Mask covered = 0;
        for (Mask s : col) {
            int k = 0;
            for (int i = 0; i < m_; ++i)
                if (s & bit(i)) sub_in_[k++] = cur_[i];
            // The subset has no plan from here, so neither has this node (a joint plan restricted
            // to the subset would be one): no successor. The predecessors learn that the subset
            // must be planned jointly earlier, as after a collision: an earlier decision of one
            // of its agents (finishing on a goal that another one must cross) may be the cause.
            if (!ctx_.planner(s).step(sub_in_.data(), sub_out_.data())) {
                const ColSet mine = nodes_[id].col;
                const std::vector<int32_t> preds = nodes_[id].backset;
                for (int32_t w : preds) backprop(w, mine);
                return;
            }
            k = 0;
            for (int i = 0; i < m_; ++i)
                if (s & bit(i)) next_[i] = sub_out_[k++];
            covered |= s;
        }
        for (int i = 0; i < m_; ++i)
            if (!(covered & bit(i))) next_[i] = policy(i, cur_[i]);
        ColSet phi;
        collisions(phi);
        if (!phi.empty()) {
            backprop(id, phi);
            return;
        }
        int32_t cost = 0;
        for (int i = 0; i < m_; ++i) cost += step_cost(i, cur_[i], next_[i]);
        const size_t known_nodes = nodes_.size();
        const int32_t u = find_or_add(next_.data());
        // A new node inherits the collision set of its predecessor: the coupled sets keep
        // following their joint plans. Without it the next node forgets the coupling, its agents
        // fall back to their policies, collide again and (under an inflated heuristic, which
        // favours the deepest node) can oscillate there for as long as other agents progress.
        // Larger collision sets keep M* complete and optimal; they only cost branching (the
        // tests check epsilon = 1 plans against an exhaustive joint search).
        if (static_cast<size_t>(u) >= known_nodes) nodes_[u].col = nodes_[id].col;
        if (nodes_[u].ctg == kDead) {
            // No plan from u: the couplings found below it (its collision set) must start here,
            // where an agent may still avoid the step that doomed u (e.g. finishing on a goal
            // that another agent must cross). Where they already do, plan all agents jointly.
            ColSet c = nodes_[u].col;
            if (c.empty() || covers(nodes_[id].col, c)) c = ColSet{mask_};
            backprop(id, c);
            return;
        }
        touch(u);
        std::vector<int32_t>& bs = nodes_[u].backset;
        if (std::find(bs.begin(), bs.end(), id) == bs.end()) bs.push_back(id);
        if (!nodes_[u].col.empty()) {
            const ColSet ucol = nodes_[u].col;
            backprop(id, ucol);
        }
        relax(id, u, nodes_[id].g + cost);
    }

    // Operator decomposition: children of the node whose agents 0..k-1 are assigned (inter_id,
    // -1 for the standard node itself), by every move of agent k. cur_ holds the parent's state.
    // No back-propagation is needed below: the parent's collision set is already all agents.
    void od_children(int32_t parent, int32_t inter_id, int32_t k, int32_t g, int32_t h) {
        for (int32_t it = inter_id, j = k - 1; j >= 0; --j) {
            asg_[j] = inter_[it].move;
            it = inter_[it].prev;
        }
        const Code c = cur_[k];
        const int32_t cc = cell_of(c);
        Code opts[7];
        int32_t costs[7];
        int no = 0;
        if (is_finished(c)) {
            opts[no] = c;
            costs[no++] = 0;
        } else {
            if (cc == p_.goal[agents_[k]] && !ctx_.free_goal_wait) {
                opts[no] = c | 1u;
                costs[no++] = 0;
            }
            opts[no] = c;
            costs[no++] = step_cost(k, c, c);
            const int32_t* nb = p_.neighbours(cc);
            for (int a = 0; a < 4 && nb[a] >= 0; ++a) {
                opts[no] = code_of(nb[a]);
                costs[no] = step_cost(k, c, opts[no]);
                ++no;
            }
        }
        const uint32_t stamp = nodes_[parent].od_stamp;
        for (int o = 0; o < no; ++o) {
            const int32_t oc = cell_of(opts[o]);
            bool clash = false;
            for (int j = 0; j < k && !clash; ++j) {
                const int32_t aj = cell_of(asg_[j]);
                clash = aj == oc || (aj == cc && oc == cell_of(cur_[j]));
            }
            if (clash) continue;
            const int32_t g2 = g + costs[o];
            const int32_t h2 = h - hd(k, c) + hd(k, opts[o]);
            if (k + 1 < m_) {
                inter_.push_back(Inter{parent, inter_id, opts[o], k + 1, g2, h2, stamp});
                if (inter_.size() > inter_peak_) {  // the arena is reused: count its peak once
                    ctx_.node_bytes += sizeof(Inter) + sizeof(Entry);
                    inter_peak_ = inter_.size();
                    if (ctx_.node_bytes > kMaxNodeBytes) throw OutOfNodes();
                }
                push_entry(Entry{g2 + ctx_.eps * h2, h2, static_cast<int32_t>(inter_.size() - 1), 0, next_tag(true)});
            } else {
                asg_[k] = opts[o];
                const int32_t u = find_or_add(asg_.data());
                if (nodes_[u].ctg == kDead) continue;
                relax(parent, u, g2);
            }
        }
    }

    void load_current(int32_t id) {
        const Code* s = state(id);
        std::copy(s, s + m_, cur_.begin());
    }

    // Marks the plan found through `id` (its back chain plus its known plan) on every node of
    // the chain: forward pointers and exact costs-to-go, reused by later queries.
    void finalize(int32_t id) {
        const int32_t total = nodes_[id].g + nodes_[id].ctg;
        for (int32_t u = id; nodes_[u].back >= 0;) {
            const int32_t b = nodes_[u].back;
            nodes_[b].forward = u;
            nodes_[b].ctg = total - nodes_[b].g;
            u = b;
        }
    }

    // A* with M*'s expansion rules from `start`; true when a plan was found (cached on nodes).
    bool search(int32_t start) {
        ++search_;
        heap_.clear();
        has_next_ = false;
        bound_ = Entry{-1.0, 0, 0, 0, 0};  // before the first pop every entry goes to the heap
        inter_.clear();
        touched_.clear();
        touch(start);
        nodes_[start].g = 0;
        push(start);
        while (has_next_ || !heap_.empty()) {
            ctx_.clock.tick();
            if (has_next_) {
                bound_ = next_entry_;
                has_next_ = false;
            } else {
                std::pop_heap(heap_.begin(), heap_.end(), ctx_.after);
                bound_ = heap_.back();
                heap_.pop_back();
            }
            const Entry e = bound_;
            if (e.inter()) {
                const Inter in = inter_[e.id];
                if (in.stamp != nodes_[in.parent].od_stamp) continue;  // parent re-expanded since
                load_current(in.parent);
                od_children(in.parent, e.id, in.k, in.g, in.h);
                continue;
            }
            Node& n = nodes_[e.id];
            if (e.ver != n.version || !n.in_open) continue;
            n.in_open = false;
            ++ctx_.expansions;
            if (n.ctg >= 0) {
                finalize(e.id);
                return true;
            }
            load_current(e.id);
            if (full(n.col)) {
                n.od_stamp = ++od_counter_;
                od_children(e.id, -1, 0, n.g, n.h);
            } else {
                expand_single(e.id);
            }
        }
        // Exhausted: every node this search reached is reachable from the start, so none of
        // them has a plan either.
        for (int32_t t : touched_)
            if (nodes_[t].g < kInf) nodes_[t].ctg = kDead;
        return false;
    }

    Context& ctx_;
    const Problem& p_;
    const Mask mask_;
    int m_ = 0;
    std::vector<int> agents_;  // agent ids, increasing: the order of codes in a state
    std::vector<Code> states_;
    std::vector<Node> nodes_;
    std::vector<uint64_t> hashes_;
    std::vector<int32_t> slots_;  // open addressing table of node ids, -1 empty
    uint32_t search_ = 0, od_counter_ = 0, seq_ = 0;
    std::vector<Entry> heap_;
    Entry bound_{}, next_entry_{};
    bool has_next_ = false;
    std::vector<Inter> inter_;
    size_t inter_peak_ = 0;
    std::vector<int32_t> touched_;
    std::vector<Code> cur_, next_, asg_, sub_in_, sub_out_;
};

Planner& Context::planner(Mask mask) {
    auto it = planners_.find(mask);
    if (it == planners_.end()) it = planners_.emplace(mask, std::make_unique<Planner>(*this, mask)).first;
    return *it->second;
}

}  // namespace

Result plan_odrmstar(const Problem& p, double epsilon, Objective objective, Clock& clock) {
    Result r;
    r.n = p.n;
    if (p.n > 64) {
        r.message = "ODrM* supports at most 64 agents (agent sets are 64-bit masks)";
        return r;
    }
    if (!(epsilon >= 1.0)) {
        r.message = "epsilon must be >= 1";
        return r;
    }
    if (p.some_goal_unreachable()) {
        r.status = kUnsolvable;
        r.message = "some agent cannot reach its goal";
        return r;
    }
    const Mask all = p.n == 64 ? ~Mask{0} : ((Mask{1} << p.n) - 1);
    std::vector<Code> start(p.n), path;
    for (int i = 0; i < p.n; ++i) start[i] = code_of(p.start[i]);
    int64_t cost = 0;
    // Two attempts, half the time limit each, differing in the order among equal f. On congested
    // cases that order decides between a plan in milliseconds and a plateau that eats the whole
    // budget, and which order wins varies from case to case. On 80 generated cases (30x30,
    // density 0.3, 64 agents, generate_instance seeds 5000-5079, 10 s): newest first alone
    // solved 72, oldest first alone 71 with different failures, the two attempts 72 (the same
    // cases as newest first). The second attempt starts afresh: reusing the collision sets of the
    // first dragged it into the same plateau.
    int64_t expansions = 0;
    auto attempt = [&](bool older_first) {
        Context ctx(p, epsilon, objective, clock);
        ctx.after.older_first = older_first;
        try {
            const bool found = ctx.planner(all).plan(start.data(), path, cost);
            expansions += ctx.expansions;
            return found;
        } catch (...) {
            expansions += ctx.expansions;
            throw;
        }
    };
    try {
        bool found = false;
        try {
            clock.set_budget(clock.limit() / 2);
            found = attempt(false);
        } catch (const OutOfNodes&) {
            throw;
        } catch (const OutOfTime&) {
            if (clock.cancelled()) throw;
            clock.set_budget(clock.limit());
            found = attempt(true);
        }
        r.status = found ? kSolved : kUnsolvable;
    } catch (const OutOfTime& e) {
        r.status = kTimeout;
        r.message = e.what();
    } catch (const std::bad_alloc&) {
        r.status = kTimeout;
        r.message = "out of memory";
    }
    r.expansions = expansions;
    if (r.status == kSolved) {
        r.cells.resize(path.size());
        for (size_t k = 0; k < path.size(); ++k) r.cells[k] = cell_of(path[k]);
        r.sum_of_costs = sum_of_costs(p, r.cells);
        // The reported cost is the plain definition. With kSumOfCosts the flag model can only
        // over-count it (a wait on the goal, not declared finished, and never followed by leaving),
        // which an inflated search may leave in its plan; with kFreeGoalWait the search cost can
        // only under-count it (waits on the goal before leaving it again).
        // With kGoalKeeping the search also adds 1 per move off a goal.
        const bool exact = objective == Objective::kSumOfCosts;
        const int64_t surcharge = objective == Objective::kGoalKeeping ? goal_leaves(p, r.cells) : 0;
        if ((exact && r.sum_of_costs > cost) || (exact && epsilon == 1.0 && r.sum_of_costs != cost) ||
            (!exact && r.sum_of_costs + surcharge < cost)) {
            r.status = kError;
            r.message = "internal error: search cost " + std::to_string(cost) + " != plan cost " +
                        std::to_string(r.sum_of_costs);
        }
    }
    return r;
}

}  // namespace mapf

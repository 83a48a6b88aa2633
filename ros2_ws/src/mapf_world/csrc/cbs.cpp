#include "cbs.hpp"

#include <algorithm>
#include <memory>
#include <queue>
#include <unordered_set>

namespace mapf {
namespace {

using Path = std::vector<int32_t>;  // cells at t = 0..T; the agent stays at back() after T
using PathPtr = std::shared_ptr<const Path>;

inline int32_t at(const Path& path, int32_t t) {
    return t < static_cast<int32_t>(path.size()) ? path[t] : path.back();
}

// Agent may not be at `to` at time t (vertex, from < 0), or may not move from -> to arriving at t.
struct Constraint {
    int32_t agent, t, from, to;
};

struct Conflict {
    int32_t a = -1, b = -1, t = 0, x = 0, y = 0;  // vertex: both at x; edge: a x->y, b y->x
    bool edge = false;
};

struct HLNode {
    int32_t parent;
    Constraint con;  // agent -1: none (the root, bypass nodes)
    int32_t agent;   // whose path this node replaced (-1 at the root)
    PathPtr path;
    int64_t cost;
    int32_t conflicts;
};

// Conflicts of a full set of paths: how many, and the earliest one.
int32_t find_conflicts(const std::vector<PathPtr>& paths, std::vector<int32_t>& who,
                       std::vector<uint32_t>& stamp, uint32_t& st, Conflict* first) {
    const int n = static_cast<int>(paths.size());
    int32_t tmax = 0;
    for (const auto& p : paths) tmax = std::max<int32_t>(tmax, static_cast<int32_t>(p->size()) - 1);
    int32_t count = 0;
    bool have_first = false;
    for (int32_t t = 0; t <= tmax; ++t) {
        if (++st == 0) {
            std::fill(stamp.begin(), stamp.end(), 0);
            st = 1;
        }
        for (int i = 0; i < n; ++i) {
            const int32_t c = at(*paths[i], t);
            if (stamp[c] == st) {
                ++count;
                if (!have_first && first) {
                    *first = Conflict{who[c], i, t, c, c, false};
                    have_first = true;
                }
            } else {
                stamp[c] = st;
                who[c] = i;
            }
        }
        if (t == 0) continue;
        // Swaps: agent i moves x -> y while the agent that was at y moves y -> x.
        if (++st == 0) {
            std::fill(stamp.begin(), stamp.end(), 0);
            st = 1;
        }
        for (int i = 0; i < n; ++i) {
            const int32_t c = at(*paths[i], t - 1);
            stamp[c] = st;
            who[c] = i;
        }
        for (int i = 0; i < n; ++i) {
            const int32_t x = at(*paths[i], t - 1), y = at(*paths[i], t);
            if (x == y || stamp[y] != st) continue;
            const int j = who[y];
            if (j > i && at(*paths[j], t) == x) {
                ++count;
                if (!have_first && first) {
                    *first = Conflict{i, j, t, x, y, true};
                    have_first = true;
                }
            }
        }
    }
    return count;
}

class LowLevel {
  public:
    LowLevel(const Problem& p, Clock& clock) : p_(p), clock_(clock), cells_(p.cells()), rest_(p.cells(), -1) {}

    // Shortest path of `agent` under `cons` (its constraints), fewest conflicts with `others`
    // among the shortest (others[agent] is ignored). False when no path exists.
    bool plan(int agent, const std::vector<Constraint>& cons, const std::vector<PathPtr>& others, Path& out) {
        vertex_.clear();
        edge_.clear();
        int32_t last_t = 0, goal_free_from = 0;
        const int32_t goal = p_.goal[agent];
        for (const Constraint& c : cons) {
            last_t = std::max(last_t, c.t);
            if (c.from < 0) {
                vertex_.insert(key(c.t, c.to));
                if (c.to == goal) goal_free_from = std::max(goal_free_from, c.t + 1);
            } else {
                edge_.insert(key(c.t, c.from) * cells_ + c.to);
            }
        }
        build_cat(agent, others);
        const int32_t horizon = last_t + cells_ + 1;
        ++search_;
        recs_.clear();
        open_ = {};
        const int32_t s = p_.start[agent];
        if (vertex_.count(key(0, s))) return false;
        add(s, 0, 0, -1);
        while (!open_.empty()) {
            clock_.tick();
            const Item it = open_.top();
            open_.pop();
            Rec& r = recs_[it.rec];
            if (r.closed) continue;
            r.closed = true;
            const int32_t cell = r.cell, t = r.t, conf = r.conf, idx = it.rec;
            if (cell == goal && t >= goal_free_from) {
                out.assign(static_cast<size_t>(t) + 1, 0);
                for (int32_t k = idx; k >= 0; k = recs_[k].parent) out[recs_[k].t] = recs_[k].cell;
                return true;
            }
            if (t + 1 > horizon) continue;
            const int32_t* nb = p_.neighbours(cell);
            for (int a = -1; a < 4; ++a) {
                const int32_t nc = a < 0 ? cell : nb[a];
                if (nc < 0) break;
                const int32_t nt = t + 1;
                if (vertex_.count(key(nt, nc))) continue;
                if (nc != cell && edge_.count(key(nt, cell) * cells_ + nc)) continue;
                const int32_t nconf = conf + cat(nc, nt) + swap_cat(cell, nc, nt);
                const int32_t found = lookup(nc, nt);
                if (found < 0) {
                    add(nc, nt, nconf, idx);
                } else if (!recs_[found].closed && nconf < recs_[found].conf) {
                    recs_[found].conf = nconf;
                    recs_[found].parent = idx;
                    push(found);
                }
            }
        }
        return false;
    }

  private:
    struct Rec {
        int32_t cell, t, conf, parent;
        bool closed;
    };
    struct Item {
        int32_t f, conf, t, rec;
    };
    struct ItemAfter {
        bool operator()(const Item& a, const Item& b) const {
            if (a.f != b.f) return a.f > b.f;
            if (a.conf != b.conf) return a.conf > b.conf;
            return a.t < b.t;  // deeper first
        }
    };

    int64_t key(int32_t t, int32_t cell) const { return static_cast<int64_t>(t) * cells_ + cell; }

    // Visited table: one layer of (stamp, record) per time step, grown on demand.
    int32_t lookup(int32_t cell, int32_t t) {
        if (t >= static_cast<int32_t>(layers_.size())) return -1;
        const auto& e = layers_[t][cell];
        return e.first == search_ ? e.second : -1;
    }
    void add(int32_t cell, int32_t t, int32_t conf, int32_t parent) {
        while (t >= static_cast<int32_t>(layers_.size()))
            layers_.emplace_back(cells_, std::pair<uint32_t, int32_t>{0, -1});
        recs_.push_back(Rec{cell, t, conf, parent, false});
        layers_[t][cell] = {search_, static_cast<int32_t>(recs_.size() - 1)};
        push(static_cast<int32_t>(recs_.size() - 1));
    }
    void push(int32_t rec) {
        const Rec& r = recs_[rec];
        open_.push(Item{r.t + p_.d(agent_of_search_, r.cell), r.conf, r.t, rec});
    }

    // Conflict-avoidance table of the other agents: occupancy per (t, cell) up to their path
    // ends, and the time from which an agent rests on its goal (rest_).
    void build_cat(int agent, const std::vector<PathPtr>& others) {
        agent_of_search_ = agent;
        for (int32_t c : rest_cells_) rest_[c] = -1;
        rest_cells_.clear();
        cat_.clear();
        others_ = &others;
        agent_ = agent;
        int32_t tmax = 0;
        for (size_t i = 0; i < others.size(); ++i)
            if (static_cast<int>(i) != agent && others[i]) tmax = std::max<int32_t>(tmax, others[i]->size());
        cat_t_ = tmax;
        cat_.assign(static_cast<size_t>(tmax) * cells_, 0);
        for (size_t i = 0; i < others.size(); ++i) {
            if (static_cast<int>(i) == agent || !others[i]) continue;
            const Path& path = *others[i];
            for (size_t t = 0; t < path.size(); ++t) ++cat_[t * cells_ + path[t]];
            const int32_t g = path.back();
            const int32_t from = static_cast<int32_t>(path.size());
            if (rest_[g] < 0) rest_cells_.push_back(g);
            rest_[g] = rest_[g] < 0 ? from : std::min(rest_[g], from);
        }
    }
    int32_t cat(int32_t cell, int32_t t) const {
        int32_t n = t < cat_t_ ? cat_[static_cast<size_t>(t) * cells_ + cell] : 0;
        if (rest_[cell] >= 0 && t >= rest_[cell]) ++n;
        return n;
    }
    int32_t swap_cat(int32_t from, int32_t to, int32_t t) const {
        if (from == to || t >= cat_t_ || cat_[static_cast<size_t>(t - 1) * cells_ + to] == 0) return 0;
        int32_t n = 0;
        for (size_t i = 0; i < others_->size(); ++i) {
            if (static_cast<int>(i) == agent_ || !(*others_)[i]) continue;
            const Path& path = *(*others_)[i];
            if (at(path, t - 1) == to && at(path, t) == from) ++n;
        }
        return n;
    }

    const Problem& p_;
    Clock& clock_;
    const int cells_;
    uint32_t search_ = 0;
    int agent_of_search_ = 0, agent_ = 0;
    std::unordered_set<int64_t> vertex_, edge_;
    std::vector<Rec> recs_;
    std::priority_queue<Item, std::vector<Item>, ItemAfter> open_;
    std::vector<std::vector<std::pair<uint32_t, int32_t>>> layers_;
    std::vector<uint16_t> cat_;
    int32_t cat_t_ = 0;
    std::vector<int32_t> rest_, rest_cells_;
    const std::vector<PathPtr>* others_ = nullptr;
};

class Cbs {
  public:
    Cbs(const Problem& p, Clock& clock)
        : p_(p), clock_(clock), low_(p, clock), who_(p.cells(), 0), stamp_(p.cells(), 0) {}

    int32_t run(std::vector<PathPtr>& solution) {
        std::vector<PathPtr> paths(p_.n);
        int64_t cost = 0;
        for (int i = 0; i < p_.n; ++i) {
            Path path;
            if (!low_.plan(i, {}, paths, path)) return kUnsolvable;
            cost += static_cast<int64_t>(path.size()) - 1;
            paths[i] = std::make_shared<const Path>(std::move(path));
        }
        root_paths_ = paths;
        nodes_.push_back(HLNode{-1, Constraint{-1, 0, -1, -1}, -1, nullptr, cost, count(paths, nullptr)});
        push(0);
        std::vector<Constraint> cons;
        while (!open_.empty()) {
            clock_.check();
            const int32_t id = open_.top().second;
            open_.pop();
            ++expansions;
            collect_paths(id, paths);
            Conflict c;
            if (count(paths, &c) == 0) {
                solution = paths;
                return kSolved;
            }
            HLNode children[2];
            int made = 0;
            bool bypass = false;
            for (int side = 0; side < 2 && !bypass; ++side) {
                const int32_t agent = side == 0 ? c.a : c.b;
                Constraint con{agent, c.t, -1, c.x};
                if (c.edge) con = side == 0 ? Constraint{agent, c.t, c.x, c.y} : Constraint{agent, c.t, c.y, c.x};
                collect_constraints(id, agent, cons);
                cons.push_back(con);
                Path path;
                if (!low_.plan(agent, cons, paths, path)) continue;
                const PathPtr old = paths[agent];
                auto np = std::make_shared<const Path>(std::move(path));
                paths[agent] = np;
                const int64_t ncost = nodes_[id].cost - static_cast<int64_t>(old->size()) + static_cast<int64_t>(np->size());
                const int32_t nconf = count(paths, nullptr);
                paths[agent] = old;
                // Bypass (Boyarski et al. 2015): a path as cheap as the old one with fewer
                // conflicts also satisfies this node's constraints, so it replaces the old one in
                // a copy of this node (no new constraint) instead of splitting.
                bypass = ncost == nodes_[id].cost && nconf < nodes_[id].conflicts;
                if (bypass) {
                    children[0] = HLNode{id, Constraint{-1, 0, -1, -1}, agent, np, ncost, nconf};
                    made = 1;
                } else {
                    children[made++] = HLNode{id, con, agent, np, ncost, nconf};
                }
            }
            for (int k = 0; k < made; ++k) {
                nodes_.push_back(children[k]);
                push(static_cast<int32_t>(nodes_.size() - 1));
            }
        }
        return kUnsolvable;  // every branch ran out of paths: the split is complete, so none exists
    }

    int64_t expansions = 0;

  private:
    struct Key {
        int64_t cost;
        int32_t conflicts;
        int32_t seq;
        bool operator>(const Key& o) const {
            if (cost != o.cost) return cost > o.cost;
            if (conflicts != o.conflicts) return conflicts > o.conflicts;
            return seq < o.seq;  // newer first among equals
        }
    };
    using Item = std::pair<Key, int32_t>;
    struct ItemAfter {
        bool operator()(const Item& a, const Item& b) const { return a.first > b.first; }
    };

    void push(int32_t id) { open_.push(Item{Key{nodes_[id].cost, nodes_[id].conflicts, id}, id}); }

    int32_t count(const std::vector<PathPtr>& paths, Conflict* first) {
        return find_conflicts(paths, who_, stamp_, st_, first);
    }

    void collect_paths(int32_t id, std::vector<PathPtr>& paths) {
        std::vector<uint8_t> done(p_.n, 0);
        for (int32_t k = id; k > 0; k = nodes_[k].parent) {
            const HLNode& n = nodes_[k];
            if (!done[n.agent]) {
                paths[n.agent] = n.path;
                done[n.agent] = 1;
            }
        }
        for (int i = 0; i < p_.n; ++i)
            if (!done[i]) paths[i] = root_paths_[i];
    }

    void collect_constraints(int32_t id, int agent, std::vector<Constraint>& cons) {
        cons.clear();
        for (int32_t k = id; k > 0; k = nodes_[k].parent)
            if (nodes_[k].con.agent == agent) cons.push_back(nodes_[k].con);
    }

    const Problem& p_;
    Clock& clock_;
    LowLevel low_;
    std::vector<HLNode> nodes_;
    std::vector<PathPtr> root_paths_;
    std::priority_queue<Item, std::vector<Item>, ItemAfter> open_;
    std::vector<int32_t> who_;
    std::vector<uint32_t> stamp_;
    uint32_t st_ = 0;
};

}  // namespace

Result plan_cbs(const Problem& p, Clock& clock) {
    Result r;
    r.n = p.n;
    if (p.some_goal_unreachable()) {
        r.status = kUnsolvable;
        r.message = "some agent cannot reach its goal";
        return r;
    }
    Cbs cbs(p, clock);
    std::vector<PathPtr> paths;
    try {
        r.status = cbs.run(paths);
    } catch (const OutOfTime& e) {
        r.status = kTimeout;
        r.message = e.what();
    } catch (const std::bad_alloc&) {
        r.status = kTimeout;
        r.message = "out of memory";
    }
    r.expansions = cbs.expansions;
    if (r.status == kSolved) {
        int32_t tmax = 0;
        for (const auto& path : paths) tmax = std::max<int32_t>(tmax, static_cast<int32_t>(path->size()) - 1);
        r.cells.resize(static_cast<size_t>(tmax + 1) * p.n);
        for (int32_t t = 0; t <= tmax; ++t)
            for (int i = 0; i < p.n; ++i) r.cells[static_cast<size_t>(t) * p.n + i] = at(*paths[i], t);
        r.sum_of_costs = sum_of_costs(p, r.cells);
    }
    return r;
}

}  // namespace mapf

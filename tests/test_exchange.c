/*
** tests/test_exchange.c -- layer 6: batching points owned by several
** processes (brt_exchange), without MPI.  Each "process" is a thread with
** its own open scene and geometry cache; an in-memory network of mailboxes
** carries the rays, and counts finished rays against the total, as
** examples/tools/mpi_trace.c does over MPI.  Hits and occlusion bytes are held
** against the direct mode (one BVH over the whole mesh), byte for byte, at
** 1 to 4 processes, both ownerships, proxies on and off, several memory
** limits, one and two threads each; a stream that crosses between
** processes many times; the ownership's balance; and the exchange's
** errors.  tests/test_mpi.c runs the same over MPI when mpirun exists.
*/
#include "test.h"
#include "util.h"

#include <pthread.h>
#include <stdlib.h>
#include <string.h>

#define MAX_PROCESSES 4

/* ---- an in-memory network ---- */

typedef struct mailbox {
    brt_ray_state *rays;
    size_t head, count, capacity;
} mailbox;

typedef struct network {
    pthread_mutex_t lock;
    pthread_cond_t changed;
    mailbox box[MAX_PROCESSES];
    const uint32_t *owner;      /* per batching point */
    uint32_t points;
    uint64_t total, finished, sent;
    brt_hit *hits;              /* by tag */
    uint8_t *occluded;          /* or occlusion bytes */
    int corrupt;                /* hand out a ray for a point owned elsewhere */
    int refuse;                 /* send fails */
} network;

typedef struct process {
    network *net;
    uint32_t rank;
    brt_scene *scene;
    uint8_t *foreign;
    const brt_ray *rays;
    size_t next, end;           /* its share of the rays */
    brt_exchange exchange;
    brt_trace_options opt;
    brt_result result;
    brt_error err;
} process;

static int net_send(void *user, const brt_ray_state *ray)
{
    process *p = user;
    network *n = p->net;
    mailbox *m = &n->box[n->owner[ray->key_point]];
    if (n->refuse) return -1;
    pthread_mutex_lock(&n->lock);
    if (m->head + m->count == m->capacity) {
        m->capacity = m->capacity ? 2 * m->capacity : 64;
        m->rays = realloc(m->rays, m->capacity * sizeof *m->rays);   /* tests: no NULL check */
    }
    m->rays[m->head + m->count++] = *ray;
    n->sent++;
    pthread_cond_broadcast(&n->changed);
    pthread_mutex_unlock(&n->lock);
    return 0;
}

/* Rays in this process's mailbox; when idle, waits for some or for every
** ray to be finished (the count against the total). */
static size_t net_receive(void *user, brt_ray_state *rays, size_t max, int idle)
{
    process *p = user;
    network *n = p->net;
    mailbox *m = &n->box[p->rank];
    size_t k = 0;
    pthread_mutex_lock(&n->lock);
    while (idle && m->count == 0 && n->finished < n->total) pthread_cond_wait(&n->changed, &n->lock);
    for (; k < max && m->count > 0; k++, m->count--) rays[k] = m->rays[m->head++];
    if (m->count == 0) m->head = 0;
    pthread_mutex_unlock(&n->lock);
    if (n->corrupt && k > 0) {   /* the first point owned elsewhere */
        uint32_t point = 0;
        while (point + 1 < n->points && n->owner[point] == p->rank) point++;
        rays[0].key_point = point;
    }
    return k;
}

static size_t share_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    process *p = user;
    size_t k;
    for (k = 0; k < max && p->next < p->end; k++, p->next++) {
        rays[k] = p->rays[p->next];
        tags[k] = p->next | (p->net->occluded ? BRT_TAG_OCCLUSION : 0);
    }
    return k;
}

static void share_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                           uint32_t visits, uint64_t tag)
{
    process *p = user;
    network *n = p->net;
    (void)ray;
    (void)normal;
    (void)visits;
    pthread_mutex_lock(&n->lock);
    if (n->occluded) n->occluded[tag & ~BRT_TAG_OCCLUSION] = hit->prim != BRT_NO_PRIM;
    else n->hits[tag] = *hit;
    if (++n->finished == n->total) pthread_cond_broadcast(&n->changed);
    pthread_mutex_unlock(&n->lock);
}

static void *process_main(void *arg)
{
    process *p = arg;
    brt_ray_source source;
    source.next_rays = share_next;
    source.finished = share_finished;
    source.user = p;
    p->result = brt_scene_trace_stream(p->scene, &p->opt, &source, NULL, &p->err);
    if (p->result != BRT_OK) {   /* a failed process must not leave the others waiting */
        pthread_mutex_lock(&p->net->lock);
        p->net->finished = p->net->total;
        pthread_cond_broadcast(&p->net->changed);
        pthread_mutex_unlock(&p->net->lock);
    }
    return NULL;
}

/* What a distributed trace is asked to do. */
typedef struct run_setup {
    uint32_t processes;
    int round_robin, no_proxy, occlusion;
    uint64_t memory;
    uint32_t rays_in_flight;
    unsigned threads;           /* per process (layer 10 with layer 6) */
    int corrupt, refuse;
} run_setup;

/* Traces rays over the scene file at path as setup->processes processes
** (each opens it); results into hits or occluded by ray.  Returns the
** first process's failure, else BRT_OK; *sent: rays sent between them. */
static brt_result run_processes(const char *path, const run_setup *setup, const brt_ray *rays,
                                size_t count, brt_hit *hits, uint8_t *occluded, uint64_t *sent,
                                brt_error *err)
{
    process procs[MAX_PROCESSES];
    pthread_t threads[MAX_PROCESSES];
    network net;
    uint32_t *owner = NULL, i, points = 0;
    brt_result r = BRT_OK;
    memset(&net, 0, sizeof net);
    memset(procs, 0, sizeof procs);
    pthread_mutex_init(&net.lock, NULL);
    pthread_cond_init(&net.changed, NULL);
    net.total = count;
    net.hits = hits;
    net.occluded = occluded;
    net.corrupt = setup->corrupt;
    net.refuse = setup->refuse;
    for (i = 0; i < setup->processes && r == BRT_OK; i++) {
        process *p = &procs[i];
        r = brt_scene_open(path, &p->scene, err);
        if (r != BRT_OK) break;
        points = brt_scene_point_count(p->scene);
        p->net = &net;
        p->rank = i;
        p->rays = rays;
        p->next = count * i / setup->processes;
        p->end = count * (i + 1) / setup->processes;
    }
    if (r == BRT_OK) {
        owner = malloc((points + 1) * sizeof *owner);
        r = brt_scene_assign(procs[0].scene, setup->processes, setup->round_robin, owner, err);
        net.owner = owner;
        net.points = points;
    }
    for (i = 0; i < setup->processes && r == BRT_OK; i++) {
        process *p = &procs[i];
        uint32_t k;
        p->foreign = malloc(points + 1);
        for (k = 0; k < points; k++) p->foreign[k] = owner[k] != i;
        p->exchange.foreign = p->foreign;
        p->exchange.send = net_send;
        p->exchange.receive = net_receive;
        p->exchange.user = p;
        p->opt.exchange = &p->exchange;
        p->opt.no_proxy = setup->no_proxy;
        p->opt.memory_limit = setup->memory;
        p->opt.threads = setup->threads ? setup->threads : 1;
        p->opt.rays_in_flight = setup->rays_in_flight;
    }
    for (i = 0; i < setup->processes && r == BRT_OK; i++)
        pthread_create(&threads[i], NULL, process_main, &procs[i]);
    for (i = 0; i < setup->processes && r == BRT_OK; i++) pthread_join(threads[i], NULL);
    for (i = 0; i < setup->processes && r == BRT_OK; i++)
        if (procs[i].result != BRT_OK) {
            r = procs[i].result;
            *err = procs[i].err;
        }
    for (i = 0; i < setup->processes; i++) {
        if (procs[i].scene) brt_scene_close(procs[i].scene);
        free(procs[i].foreign);
        free(net.box[i].rays);
    }
    free(owner);
    pthread_mutex_destroy(&net.lock);
    pthread_cond_destroy(&net.changed);
    if (sent) *sent = net.sent;
    return r;
}

/* ---- the reference ---- */

typedef struct fixture {
    tu_scene scene;
    brt_ray *rays;
    brt_hit *direct;
    uint8_t *direct_occluded;
    size_t count;
    char path[4096];
} fixture;

/* A soup of triangles in batching points of point_tris, rays of every
** kind, and the direct mode's hits and occlusion bytes. */
static int fixture_make(fixture *f, uint32_t triangles, float size, uint32_t point_tris,
                        size_t per_kind, const char *name)
{
    brt_scene *scene;
    brt_bvh *bvh = NULL;
    float lo[3], hi[3];
    uint64_t st = test_seed();
    size_t i;
    int kind;
    memset(f, 0, sizeof *f);
    tu_random_soup(&f->scene, &st, triangles, size);
    snprintf(f->path, sizeof f->path, "%s", tu_scratch(name));
    scene = tu_build_scene(&f->scene, point_tris, 32, 1, f->path);
    if (!scene) return 0;
    brt_scene_close(scene);
    tu_scene_bounds(&f->scene, lo, hi);
    f->count = per_kind * TU_RAY_KINDS;
    f->rays = malloc(f->count * sizeof *f->rays);
    f->direct = malloc(f->count * sizeof *f->direct);
    f->direct_occluded = malloc(f->count);
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++)
            tu_make_ray(&f->scene, lo, hi, kind, &st, &f->rays[(size_t)kind * per_kind + i]);
    if (brt_bvh_build(f->scene.pos, f->scene.idx, f->scene.tcount, NULL, &bvh) != BRT_OK) return 0;
    for (i = 0; i < f->count; i++) {
        brt_hit_clear(&f->direct[i]);
        brt_bvh_intersect(bvh, &f->rays[i], &f->direct[i]);
        f->direct_occluded[i] = (uint8_t)brt_bvh_occluded(bvh, &f->rays[i]);
    }
    brt_bvh_free(bvh);
    return 1;
}

static void fixture_free(fixture *f)
{
    tu_scene_free(&f->scene);
    free(f->rays);
    free(f->direct);
    free(f->direct_occluded);
}

/* One distributed run against the direct mode; returns the rays sent. */
static uint64_t expect_direct(const fixture *f, const run_setup *setup)
{
    brt_hit *hits = malloc(f->count * sizeof *hits);
    uint8_t *occluded = malloc(f->count);
    uint64_t sent = 0;
    brt_error err;
    brt_result r;
    memset(hits, 0xAB, f->count * sizeof *hits);
    memset(occluded, 7, f->count);
    r = run_processes(f->path, setup, f->rays, f->count, setup->occlusion ? NULL : hits,
                      setup->occlusion ? occluded : NULL, &sent, &err);
    EXPECT(r == BRT_OK, "%u processes: %s", setup->processes, err.message);
    if (setup->occlusion)
        EXPECT(memcmp(occluded, f->direct_occluded, f->count) == 0,
               "%u processes%s%s, memory %llu: occlusion bytes differ from the direct mode",
               setup->processes, setup->round_robin ? ", round robin" : "",
               setup->no_proxy ? ", no proxies" : "", (unsigned long long)setup->memory);
    else
        EXPECT(memcmp(hits, f->direct, f->count * sizeof *hits) == 0,
               "%u processes%s%s, memory %llu: hits differ from the direct mode", setup->processes,
               setup->round_robin ? ", round robin" : "", setup->no_proxy ? ", no proxies" : "",
               (unsigned long long)setup->memory);
    free(hits);
    free(occluded);
    return sent;
}

/* ---- tests ---- */

static void test_equal_direct(void)
{
    fixture f;
    run_setup s;
    uint32_t processes;
    int variant;
    CHECK(fixture_make(&f, 3000, 0.04f, 60, 300, "exchange.brs"), "fixture");
    for (processes = 1; processes <= MAX_PROCESSES; processes++)
        for (variant = 0; variant < 8; variant++) {
            memset(&s, 0, sizeof s);
            s.processes = processes;
            s.round_robin = variant & 1;
            s.no_proxy = (variant >> 1) & 1;
            s.occlusion = (variant >> 2) & 1;
            s.memory = variant % 3 == 0 ? 0 : 8192;   /* all, or about one point */
            s.rays_in_flight = variant % 3 == 1 ? 7 : 0;
            s.threads = variant % 4 == 3 ? 2 : 1;
            expect_direct(&f, &s);
        }
    fixture_free(&f);
}

/* Points of 4 large triangles owned round robin: rays enter many boxes
** before a hit, crossing between the processes many times, and still
** find the direct mode's hits. */
static void test_many_crossings(void)
{
    fixture f;
    run_setup s;
    uint64_t sent;
    CHECK(fixture_make(&f, 4000, 0.3f, 4, 200, "crossings.brs"), "fixture");
    memset(&s, 0, sizeof s);
    s.processes = 3;
    s.round_robin = 1;
    s.no_proxy = 1;      /* every box entered is a stop: the most crossings */
    s.rays_in_flight = 16;
    sent = expect_direct(&f, &s);
    EXPECT(sent >= 10 * f.count, "only %llu rays sent for %lu rays", (unsigned long long)sent,
           (unsigned long)f.count);
    s.no_proxy = 0;
    EXPECT(expect_direct(&f, &s) < sent, "proxies did not cut the rays sent");
    fixture_free(&f);
}

/* Runs: every process owns points, and no process more bytes than its
** share plus one point; round robin deals the points in turn. */
static void test_assign(void)
{
    fixture f;
    brt_scene *scene;
    brt_error err;
    uint32_t owner[4096], counts[MAX_PROCESSES], n, i, p;
    CHECK(fixture_make(&f, 3000, 0.04f, 25, 1, "assign.brs"), "fixture");
    CHECK(brt_scene_open(f.path, &scene, &err) == BRT_OK, "%s", err.message);
    n = brt_scene_point_count(scene);
    CHECK(n > 8 && n < 4096, "%u points", n);
    for (p = 1; p <= MAX_PROCESSES; p++) {
        uint32_t most = 0, least = n;
        CHECK(brt_scene_assign(scene, p, 0, owner, &err) == BRT_OK, "%s", err.message);
        memset(counts, 0, sizeof counts);
        for (i = 0; i < n; i++) {
            CHECK(owner[i] < p, "point %u to process %u of %u", i, owner[i], p);
            counts[owner[i]]++;
        }
        for (i = 0; i < p; i++) {
            if (counts[i] > most) most = counts[i];
            if (counts[i] < least) least = counts[i];
        }
        /* Points of 25 triangles weigh about the same: runs within two. */
        EXPECT(least > 0 && most - least <= 2, "%u processes: runs of %u to %u points", p, least, most);
        CHECK(brt_scene_assign(scene, p, 1, owner, &err) == BRT_OK, "%s", err.message);
        memset(counts, 0, sizeof counts);
        for (i = 0; i < n; i++) counts[owner[i]]++;
        for (i = 0; i < p; i++) EXPECT(counts[i] == n / p + (i < n % p), "round robin: %u", counts[i]);
    }
    EXPECT(brt_scene_assign(scene, 0, 0, owner, &err) == BRT_EARG, "0 processes accepted");
    brt_scene_close(scene);
    fixture_free(&f);
}

/* A ray for a point not owned here, and a send that fails: errors. */
static void test_exchange_errors(void)
{
    fixture f;
    run_setup s;
    brt_hit *hits;
    brt_error err;
    CHECK(fixture_make(&f, 500, 0.04f, 40, 50, "exchange-errors.brs"), "fixture");
    hits = malloc(f.count * sizeof *hits);
    memset(&s, 0, sizeof s);
    s.processes = 2;
    s.corrupt = 1;
    EXPECT(run_processes(f.path, &s, f.rays, f.count, hits, NULL, NULL, &err) == BRT_EFORMAT &&
               strstr(err.message, "not owned here"),
           "a foreign point's ray accepted: '%s'", err.message);
    s.corrupt = 0;
    s.refuse = 1;
    EXPECT(run_processes(f.path, &s, f.rays, f.count, hits, NULL, NULL, &err) == BRT_EIO &&
               strstr(err.message, "could not be sent"),
           "a failed send not reported: '%s'", err.message);
    free(hits);
    fixture_free(&f);
}

void suite_exchange(void)
{
    test_run("exchange: == direct at 1-4 processes, ownerships, proxies, memory", test_equal_direct);
    test_run("exchange: rays crossing between processes many times", test_many_crossings);
    test_run("exchange: ownership runs balanced, round robin in turn", test_assign);
    test_run("exchange: a ray for a point owned elsewhere, a failed send", test_exchange_errors);
}

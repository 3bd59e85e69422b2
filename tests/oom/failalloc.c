/*
** tests/oom/failalloc.c -- an allocation-failure shim for the "oom:" tests.
**
** Loaded with LD_PRELOAD into one program run, it makes the N-th call of
** malloc, calloc, realloc or posix_memalign fail (BRT_FAIL_ALLOC=N,
** counted from the start of the process), once, as SQLite's fault
** injection fails the N-th allocation.  It records that it did, by
** writing N to the file BRT_FAIL_ALLOC_LOG: a run that leaves no record
** made fewer than N allocations, so the sweep N = 1, 2, ... ends there.
** The real allocations are glibc's own entry points (__libc_malloc ...),
** so no dlsym is needed.  Elsewhere than glibc the file defines nothing,
** no record is ever written, and the tests SKIP.
*/
#if defined(__GLIBC__) || defined(__linux__)
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#endif
#ifdef __GLIBC__

extern void *__libc_malloc(size_t size);
extern void *__libc_calloc(size_t count, size_t size);
extern void *__libc_realloc(void *old, size_t size);
extern void *__libc_memalign(size_t alignment, size_t size);

static long fail_at = -1;   /* -1: not read yet; 0: never fail */
static long calls;

/* Is this call the one to fail?  getenv, open and write allocate nothing,
** so they are safe inside malloc. */
static int fail_now(void)
{
    long n;
    if (fail_at < 0) {
        const char *s = getenv("BRT_FAIL_ALLOC");
        fail_at = s ? atol(s) : 0;
    }
    n = __sync_add_and_fetch(&calls, 1);   /* threads may allocate too */
    if (fail_at <= 0 || n != fail_at) return 0;
    {
        const char *log = getenv("BRT_FAIL_ALLOC_LOG");
        int fd = log ? open(log, O_WRONLY | O_CREAT | O_TRUNC, 0644) : -1;
        char text[32];
        int len = snprintf(text, sizeof text, "%ld\n", n);
        if (fd >= 0) {
            if (write(fd, text, (size_t)len) != len) { /* the sweep then ends early: visible */ }
            close(fd);
        }
    }
    errno = ENOMEM;
    return 1;
}

void *malloc(size_t size) { return fail_now() ? NULL : __libc_malloc(size); }
void *calloc(size_t count, size_t size) { return fail_now() ? NULL : __libc_calloc(count, size); }
void *realloc(void *old, size_t size) { return fail_now() ? NULL : __libc_realloc(old, size); }

int posix_memalign(void **out, size_t alignment, size_t size)
{
    void *m;
    if (fail_now()) return ENOMEM;
    if (!(m = __libc_memalign(alignment, size))) return ENOMEM;
    *out = m;
    return 0;
}
#else
typedef int failalloc_is_empty_here;   /* ISO C wants a declaration */
#endif

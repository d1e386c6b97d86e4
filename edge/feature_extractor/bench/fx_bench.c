/* Timing helpers for `make bench-edge` (host/flytrack_host/edges/features/bench.py), built as
 * libflytrack_features_bench.so with the extractor's own compiler flags.
 *
 * The C extractor and its floor are timed here, per frame with the monotonic clock, so that
 * neither carries a foreign-call overhead and both are timed the same way:
 *  - the floor is one read pass over the frame: an OR of all its bytes, 64-byte vectors from the
 *    first aligned address, four accumulators (as fast as this machine reads);
 *  - warm = 1 reads the frame once, untimed, before each timed call: the frame is in cache, as
 *    when the same buffer was just written by the CPU. warm = 0 leaves it as it is: over a ring of
 *    buffers larger than the caches it comes from memory, as a frame a camera just wrote by DMA.
 * The extractor is called through the address of ft_fx_process that the caller loaded (ctypes), so
 * this library times exactly the code the host and the daemon run.
 */
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

/* may_alias: the frame is bytes, read here as 64-byte vectors. */
typedef uint64_t v8x64 __attribute__((vector_size(64), may_alias));

uint64_t ft_bench_read_pass(const void *buf, size_t n) {
    const uint8_t *p = buf, *e = p + n;
    uint64_t head = 0;
    while (p < e && ((uintptr_t)p & 63u))
        head |= *p++;
    v8x64 a = {0}, b = {0}, c = {0}, d = {0};
    for (; p + 256 <= e; p += 256) {
        const v8x64 *q = __builtin_assume_aligned(p, 64);
        a |= q[0];
        b |= q[1];
        c |= q[2];
        d |= q[3];
    }
    for (; p + 64 <= e; p += 64)
        a |= *(const v8x64 *)__builtin_assume_aligned(p, 64);
    a |= b | c | d;
    uint64_t out = head;
    for (unsigned i = 0; i < 8; i++)
        out |= a[i];
    while (p < e)
        out |= *p++;
    return out;
}

static uint64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000u + (uint64_t)t.tv_nsec;
}

static volatile uint64_t sink; /* keeps the read passes */

typedef int (*process_fn)(void *fx, const void *frame, size_t nbytes, void *result);

/* Calls process(fx, frames[(start + i) % nframes], nbytes, result) for i < count; ns[i] gets each
 * call's time. Returns 0, or the first nonzero result code (timing stops there). */
int ft_bench_time_process(void *process, void *fx, void *result, const void *const *frames,
                          size_t nframes, size_t start, size_t count, size_t nbytes, int warm,
                          uint64_t *ns) {
    process_fn fn;
    memcpy(&fn, &process, sizeof fn);
    for (size_t i = 0; i < count; i++) {
        const void *f = frames[(start + i) % nframes];
        if (warm)
            sink += ft_bench_read_pass(f, nbytes);
        uint64_t t0 = now_ns();
        int rc = fn(fx, f, nbytes, result);
        ns[i] = now_ns() - t0;
        if (rc)
            return rc;
    }
    return 0;
}

/* The floor: one read pass over the same frames, in the same cache state. */
void ft_bench_time_read(const void *const *frames, size_t nframes, size_t start, size_t count,
                        size_t nbytes, int warm, uint64_t *ns) {
    for (size_t i = 0; i < count; i++) {
        const void *f = frames[(start + i) % nframes];
        if (warm)
            sink += ft_bench_read_pass(f, nbytes);
        uint64_t t0 = now_ns();
        sink += ft_bench_read_pass(f, nbytes);
        ns[i] = now_ns() - t0;
    }
}

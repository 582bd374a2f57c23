/* Peak arithmetic rate of ONE core on 512-bit instructions: FMA fp32 (VFMADD), bf16 dot products
 * (VDPBF16PS) and int8 dot products (VPDPBUSD, VNNI), on 16 independent register-only chains
 * (no memory traffic), timed in thread CPU time so that time spent descheduled on a shared
 * machine does not count. Prints one JSON object. tools/bench_backbone.py compiles and runs it
 * (gcc -O2 -march=native) on every core at once; its numbers are the "physical limit" of the
 * backbone table in the README.
 *
 * FLOP counts: an FMA lane is 2 FLOP; VDPBF16PS does 2 bf16 products + 2 adds per fp32 lane;
 * VPDPBUSD does 4 u8 x s8 products + 4 adds per int32 lane. */
#include <immintrin.h>
#include <stdio.h>
#include <time.h>

#define CHAINS 16

static double cpu_seconds(void) {
    struct timespec t;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

__attribute__((noinline)) static float fp32_fma(long iterations) {
    __m512 acc[CHAINS];
    const __m512 b = _mm512_set1_ps(1.0001f), c = _mm512_set1_ps(0.9999f);
    for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_set1_ps((float)i);
    for (long k = 0; k < iterations; k++) {
#pragma GCC unroll 16
        for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_fmadd_ps(acc[i], b, c);
    }
    __m512 s = acc[0];
    for (int i = 1; i < CHAINS; i++) s = _mm512_add_ps(s, acc[i]);
    return _mm512_reduce_add_ps(s);
}

__attribute__((noinline)) static float bf16_dot(long iterations) {
    __m512 acc[CHAINS];
    const __m512bh b = (__m512bh)_mm512_set1_epi16(0x3f80), c = (__m512bh)_mm512_set1_epi16(0x3f80);
    for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_set1_ps((float)i);
    for (long k = 0; k < iterations; k++) {
#pragma GCC unroll 16
        for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_dpbf16_ps(acc[i], b, c);
    }
    __m512 s = acc[0];
    for (int i = 1; i < CHAINS; i++) s = _mm512_add_ps(s, acc[i]);
    return _mm512_reduce_add_ps(s);
}

__attribute__((noinline)) static int int8_dot(long iterations) {
    __m512i acc[CHAINS];
    const __m512i b = _mm512_set1_epi8(1), c = _mm512_set1_epi8(1);
    for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_set1_epi32(i);
    for (long k = 0; k < iterations; k++) {
#pragma GCC unroll 16
        for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_dpbusd_epi32(acc[i], b, c);
    }
    __m512i s = acc[0];
    for (int i = 1; i < CHAINS; i++) s = _mm512_add_epi32(s, acc[i]);
    return _mm512_reduce_add_epi32(s);
}

int main(void) {
    const long iterations = 20000000;
    double best[3] = {0, 0, 0};
    volatile float sink_f = 0;
    volatile int sink_i = 0;
    for (int r = 0; r < 3; r++) {
        double t = cpu_seconds();
        sink_f += fp32_fma(iterations);
        double g = (double)iterations * CHAINS * 16 * 2 / (cpu_seconds() - t) / 1e9;
        if (g > best[0]) best[0] = g;
        t = cpu_seconds();
        sink_f += bf16_dot(iterations);
        g = (double)iterations * CHAINS * 16 * 4 / (cpu_seconds() - t) / 1e9;
        if (g > best[1]) best[1] = g;
        t = cpu_seconds();
        sink_i += int8_dot(iterations);
        g = (double)iterations * CHAINS * 16 * 8 / (cpu_seconds() - t) / 1e9;
        if (g > best[2]) best[2] = g;
    }
    printf("{\"fp32\": %.1f, \"bf16\": %.1f, \"int8\": %.1f}\n", best[0], best[1], best[2]);
    return 0;
}

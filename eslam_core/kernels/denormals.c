/* Flush-to-zero of denormal floats, switched on or off in every thread of the OpenMP pool (see eslam_core/cpu.py).
 *
 * The flag is per thread (x86 MXCSR FTZ/DAZ, ARM FPCR FZ); torch's own switch sets it only in the calling thread,
 * and its worker threads are the OpenMP pool this library shares with torch. Returns how many threads were set.
 */
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif
#if defined(__x86_64__) || defined(__i386__)
#include <xmmintrin.h>
static void set_this_thread(int on) {
    const unsigned int bits = 0x8040; /* FTZ | DAZ */
    _mm_setcsr(on ? (_mm_getcsr() | bits) : (_mm_getcsr() & ~bits));
}
#elif defined(__aarch64__)
static void set_this_thread(int on) {
    uint64_t fpcr, bit = 1ull << 24;
    __asm__ volatile("mrs %0, fpcr" : "=r"(fpcr));
    fpcr = on ? (fpcr | bit) : (fpcr & ~bit);
    __asm__ volatile("msr fpcr, %0" : : "r"(fpcr));
}
#else
static void set_this_thread(int on) { (void)on; }
#endif

int set_flush_denormals(int on, int threads) {
    int n = 0;
    #pragma omp parallel num_threads(threads) reduction(+:n)
    {
        set_this_thread(on);
        n += 1;
    }
    return n;
}

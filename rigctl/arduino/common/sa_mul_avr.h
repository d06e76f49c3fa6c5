/* sa_mul_avr.h - the integer SA kernel's products as inline AVR MUL code (sa_encoder.c, -DSA_FIXED -DSA_MUL_AVR).
 *
 * The portable encoder computes its 16 x 16 -> 32-bit products in plain C; avr-gcc turns each into a call of a
 * libgcc routine (__mulhisi3, __umulhisi3, __usmulhisi3: ~35 cycles with the register moves around it) and the
 * input's 32-bit product into __mulsi3 (~60). The AVR builds define SA_MUL_AVR, and sa_encoder.c takes these instead:
 * the same integers (two's complement products, exact: no rounding anywhere), computed inline with the core's
 * MUL / MULS / MULSU (2 cycles each): Atmel application note AVR201, "Using the AVR Hardware Multiplier"
 * (muls16x16_32). MULS and MULSU take only r16-r23 ("a" constraint). MULSU leaves the sign of its product in C,
 * which SBC folds into the top byte (the partial product's sign extension). r1 (avr-gcc's zero register) is
 * cleared after use. Only for cores with a multiplier (every ATmega; not the ATtiny).
 */
#ifndef RIGCTL_SA_MUL_AVR_H
#define RIGCTL_SA_MUL_AVR_H
#include <stdint.h>

#if !defined(__AVR_HAVE_MUL__)
#error "sa_mul_avr.h needs an AVR core with the hardware multiplier"
#endif

/* add the partial product r1:r0 to bytes 1-3 of the result (z = 0); _SIGNED first folds MULSU's sign (in C) into
 * the top byte */
#define SA_MUL_ACC "add %B[r], r0\n\tadc %C[r], r1\n\tadc %D[r], %[z]\n\t"
#define SA_MUL_ACC_SIGNED "sbc %D[r], %[z]\n\t" SA_MUL_ACC

/* (int32) a * b, a and b signed */
static inline __attribute__((always_inline)) int32_t sa_mul_ss(int16_t a, int16_t b) {
    int32_t r;
    uint8_t z;
    __asm__("clr %[z]"                 "\n\t"
            "muls %B[a], %B[b]"        "\n\t"
            "movw %C[r], r0"           "\n\t"
            "mul %A[a], %A[b]"         "\n\t"
            "movw %A[r], r0"           "\n\t"
            "mulsu %B[a], %A[b]"       "\n\t"
            SA_MUL_ACC_SIGNED
            "mulsu %B[b], %A[a]"       "\n\t"
            SA_MUL_ACC_SIGNED
            "clr r1"
            : [r] "=&r"(r), [z] "=&r"(z)
            : [a] "a"(a), [b] "a"(b));
    return r;
}

/* (int32) a * b, a signed, b unsigned */
static inline __attribute__((always_inline)) int32_t sa_mul_su(int16_t a, uint16_t b) {
    int32_t r;
    uint8_t z;
    __asm__("clr %[z]"                 "\n\t"
            "mulsu %B[a], %B[b]"       "\n\t"
            "movw %C[r], r0"           "\n\t"
            "mul %A[a], %A[b]"         "\n\t"
            "movw %A[r], r0"           "\n\t"
            "mulsu %B[a], %A[b]"       "\n\t"
            SA_MUL_ACC_SIGNED
            "mul %B[b], %A[a]"         "\n\t"
            SA_MUL_ACC
            "clr r1"
            : [r] "=&r"(r), [z] "=&r"(z)
            : [a] "a"(a), [b] "a"(b));
    return r;
}

/* (uint32) a * b, both unsigned */
static inline __attribute__((always_inline)) uint32_t sa_mul_uu(uint16_t a, uint16_t b) {
    uint32_t r;
    uint8_t z;
    __asm__("clr %[z]"                 "\n\t"
            "mul %B[a], %B[b]"         "\n\t"
            "movw %C[r], r0"           "\n\t"
            "mul %A[a], %A[b]"         "\n\t"
            "movw %A[r], r0"           "\n\t"
            "mul %B[a], %A[b]"         "\n\t"
            SA_MUL_ACC
            "mul %B[b], %A[a]"         "\n\t"
            SA_MUL_ACC
            "clr r1"
            : [r] "=&r"(r), [z] "=&r"(z)
            : [a] "r"(a), [b] "r"(b));
    return r;
}

#endif

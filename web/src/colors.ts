// matplotlib's "coolwarm" diverging map (the one the figures use), sampled at 11 points.
const COOLWARM: [number, number, number][] = [
  [59, 76, 192], [89, 119, 227], [123, 159, 249], [158, 190, 255], [192, 212, 245], [221, 220, 220],
  [242, 203, 183], [247, 172, 142], [238, 132, 104], [214, 82, 68], [180, 4, 38],
];
export const NEUTRAL = "#bfbfbf";

/** Colour of t in [0, 1] as "rgb(r, g, b)". */
export function coolwarm(t: number): string {
  const x = Math.min(1, Math.max(0, t)) * (COOLWARM.length - 1);
  const i = Math.min(COOLWARM.length - 2, Math.floor(x));
  const f = x - i;
  const c = COOLWARM[i].map((a, k) => Math.round(a + f * (COOLWARM[i + 1][k] - a)));
  return `rgb(${c[0]}, ${c[1]}, ${c[2]})`;
}

/** Symmetric scale of the lateral bending angles (at least ±1°). */
export function bendingLimit(values: (number | null)[]): number {
  return Math.max(1, ...values.filter((v): v is number => v !== null).map(Math.abs));
}

export function bendingColour(value: number | null, limit: number): string {
  return value === null ? NEUTRAL : coolwarm((value / limit + 1) / 2);
}

export function gradientCss(): string {
  return `linear-gradient(to right, ${COOLWARM.map((c, i) => `rgb(${c.join(",")}) ${(i * 10).toFixed(0)}%`).join(", ")})`;
}

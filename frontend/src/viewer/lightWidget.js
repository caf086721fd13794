/**
 * The light-direction widget: the hemisphere of light directions seen from the camera, drawn
 * as a disc with the image's orientation (x right, y down), so the dot sits where the light
 * comes from: at the bottom of the disc for φ = 0° (SCAN_BUNDLE.md). Drag to move the light;
 * the centre is light from the camera, the rim is grazing light. Focusable: arrow keys move
 * the light as everywhere in the viewer.
 */
import { anglesToDisc, discToAngles } from './light.js';

/**
 * @param {HTMLCanvasElement} canvas square canvas
 * @param {{onInput: (angles: {azimuthDeg: number, polarDeg: number}) => void}} options
 * @returns {{draw: (light: {azimuthDeg: number, polarDeg: number}) => void, dispose: () => void}}
 */
export function createLightWidget(canvas, { onInput }) {
  const ctx = canvas.getContext('2d');
  let current = { azimuthDeg: 0, polarDeg: 45 };
  let dragging = false;

  function geometry() {
    const size = canvas.width;
    return { c: size / 2, r: size / 2 - 8 };
  }

  function draw(light) {
    current = light;
    const { c, r } = geometry();
    const dpr = canvas.width / (canvas.clientWidth || canvas.width);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    const grad = ctx.createRadialGradient(c, c, r * 0.05, c, c, r);
    grad.addColorStop(0, '#4a4f59');
    grad.addColorStop(1, '#23262d');
    ctx.fillStyle = grad;
    ctx.beginPath();
    ctx.arc(c, c, r, 0, 2 * Math.PI);
    ctx.fill();
    ctx.strokeStyle = '#6b7280';
    ctx.lineWidth = dpr;
    for (const polar of [30, 60]) {
      ctx.beginPath();
      ctx.arc(c, c, r * Math.sin((polar * Math.PI) / 180), 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.beginPath();
    ctx.moveTo(c - r, c);
    ctx.lineTo(c + r, c);
    ctx.moveTo(c, c - r);
    ctx.lineTo(c, c + r);
    ctx.stroke();
    const [dx, dy] = anglesToDisc(light.azimuthDeg, light.polarDeg);
    // A light behind the view plane (θ > 90°) projects inside the disc too: drawn hollow.
    const behind = light.polarDeg > 90;
    ctx.fillStyle = '#ffd54a';
    ctx.strokeStyle = behind ? '#ffd54a' : '#000';
    ctx.lineWidth = (behind ? 3 : 1) * dpr;
    ctx.beginPath();
    ctx.arc(c + dx * r, c + dy * r, 7 * dpr, 0, 2 * Math.PI);
    if (!behind) ctx.fill();
    ctx.stroke();
    canvas.setAttribute(
      'aria-valuetext',
      `azimuth ${light.azimuthDeg.toFixed(0)} degrees, polar ${light.polarDeg.toFixed(0)} degrees` +
        `${behind ? ', from behind' : ''}, relative to the view`,
    );
  }

  function fromEvent(event) {
    const rect = canvas.getBoundingClientRect();
    const { c, r } = geometry();
    const sx = canvas.width / rect.width;
    const x = (event.clientX - rect.left) * sx;
    const y = (event.clientY - rect.top) * sx;
    onInput(discToAngles((x - c) / r, (y - c) / r));
  }

  const down = (e) => {
    dragging = true;
    canvas.setPointerCapture(e.pointerId);
    fromEvent(e);
  };
  const move = (e) => dragging && fromEvent(e);
  const up = (e) => {
    dragging = false;
    if (canvas.hasPointerCapture(e.pointerId)) canvas.releasePointerCapture(e.pointerId);
  };
  canvas.addEventListener('pointerdown', down);
  canvas.addEventListener('pointermove', move);
  canvas.addEventListener('pointerup', up);
  canvas.addEventListener('pointercancel', up);
  draw(current);

  return {
    draw,
    dispose() {
      canvas.removeEventListener('pointerdown', down);
      canvas.removeEventListener('pointermove', move);
      canvas.removeEventListener('pointerup', up);
      canvas.removeEventListener('pointercancel', up);
    },
  };
}

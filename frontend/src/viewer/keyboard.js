/**
 * Keyboard shortcuts of the viewer, as data: the help dialog and docs/viewer.md list exactly
 * these. `action` names are dispatched by the tablet page (viewer/ui.js).
 */

export const SHORTCUTS = Object.freeze([
  { keys: ['ArrowLeft', 'ArrowRight'], label: '← →', action: 'light-azimuth', help: 'turn the light around the tablet (5°; with Shift 1°)' },
  { keys: ['ArrowUp', 'ArrowDown'], label: '↑ ↓', action: 'light-polar', help: 'raise / lower the light (5°; with Shift 1°)' },
  { keys: ['1', '2', '3', '4', '5', '6', '7', '8'], label: '1 … 8', action: 'raking', help: 'raking light from the bottom, bottom-right, right, … of the view (every 45°)' },
  { keys: ['9'], label: '9', action: 'overhead', help: 'light from the camera direction, following the camera' },
  { keys: ['+', '='], label: '+', action: 'brighter', help: 'brighter light' },
  { keys: ['-'], label: '−', action: 'dimmer', help: 'dimmer light' },
  { keys: ['g'], label: 'G', action: 'gloss', help: 'specular enhancement on / off' },
  { keys: ['n'], label: 'N', action: 'mode:natural', help: 'natural colour' },
  { keys: ['c'], label: 'C', action: 'mode:clay', help: 'plain clay' },
  { keys: ['v'], label: 'V', action: 'mode:curvature', help: 'curvature (press again for the next scale)' },
  { keys: ['a'], label: 'A', action: 'mode:accessibility', help: 'accessibility (ambient occlusion)' },
  { keys: ['e'], label: 'E', action: 'mode:relief', help: 'relief: unsharp-masked normals' },
  { keys: ['d'], label: 'D', action: 'mode:depth', help: 'depth on a colour ramp, exaggerated' },
  { keys: ['N'], label: 'Shift+N', action: 'mode:normals', help: 'normal map' },
  { keys: ['q'], label: 'Q', action: 'mode:quality', help: 'quality map of the reconstruction' },
  { keys: ['u'], label: 'U', action: 'mode:trust', help: 'trust: where the heights come from, how far they hold' },
  { keys: ['j'], label: 'J', action: 'lens', help: 'lens: another shading mode in a movable circle' },
  { keys: ['w'], label: 'W', action: 'best-light', help: 'best light for a region (click its middle)' },
  { keys: ['x'], label: 'X', action: 'section', help: 'section along a line (click two points), SVG export' },
  { keys: ['o'], label: 'O', action: 'view:obverse', help: 'obverse' },
  { keys: ['r'], label: 'R', action: 'view:reverse', help: 'reverse (turned over the bottom edge)' },
  { keys: ['t'], label: 'T', action: 'view:top', help: 'top edge' },
  { keys: ['b'], label: 'B', action: 'view:bottom', help: 'bottom edge' },
  { keys: ['l'], label: 'L', action: 'view:left', help: 'left edge' },
  { keys: ['i'], label: 'I', action: 'view:right', help: 'right edge' },
  { keys: ['0', 'Home'], label: '0 / Home', action: 'reset', help: 'reset the view' },
  { keys: [']'], label: ']', action: 'zoom-in', help: 'zoom in' },
  { keys: ['['], label: '[', action: 'zoom-out', help: 'zoom out' },
  { keys: ['.'], label: '.', action: 'turn-right', help: 'turn the tablet 15° to the right' },
  { keys: [','], label: ',', action: 'turn-left', help: 'turn the tablet 15° to the left' },
  { keys: ['p'], label: 'P', action: 'projection', help: 'orthographic ↔ perspective' },
  { keys: ['m'], label: 'M', action: 'measure', help: 'measure a distance (click two points)' },
  { keys: ['h'], label: 'H', action: 'profile', help: 'height profile (click two points)' },
  { keys: ['Escape'], label: 'Esc', action: 'cancel', help: 'stop measuring, close dialogs' },
  { keys: ['s'], label: 'S', action: 'screenshot', help: 'save a screenshot (PNG)' },
  { keys: ['k'], label: 'K', action: 'permalink', help: 'copy the permalink of this view' },
  { keys: ['?'], label: '?', action: 'help', help: 'show these shortcuts' },
]);

const BY_KEY = new Map();
for (const s of SHORTCUTS) for (const k of s.keys) BY_KEY.set(k, s);

/**
 * The action for a keyboard event, or null. Keys typed into form fields are not shortcuts.
 * @param {{key: string, ctrlKey?: boolean, metaKey?: boolean, altKey?: boolean, target?: any}} event
 * @returns {{action: string, key: string, fine: boolean} | null}
 */
export function actionForKey(event) {
  if (event.ctrlKey || event.metaKey || event.altKey) return null;
  const tag = event.target?.tagName;
  if (tag === 'INPUT' || tag === 'TEXTAREA' || tag === 'SELECT' || event.target?.isContentEditable) {
    return null;
  }
  const s = BY_KEY.get(event.key);
  if (!s) return null;
  return { action: s.action, key: event.key, fine: Boolean(event.shiftKey) };
}
